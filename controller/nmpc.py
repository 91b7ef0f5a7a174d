"""NMPC: steering MPC on the nonlinear single-track model with Magic Formula tyres
(paper Section IV-B 2)), solved to convergence by IPOPT through CasADi.

Multiple shooting over Np steps: the shooting states are [vx, vy, yaw_rate, X, Y, yaw],
each interval integrated by one RK4 step of Ts of the single-track derivatives plus the
continuous pose kinematics (eq. 20's Euler step is the first-order version of this). The
torque is the P controller's value held over the horizon; the steer is held after Nc. Same
cost and soft state bounds as the QP controllers. The NLP is built once (SX, expanded);
each step passes parameters and warm-starts from the shifted previous solution and
multipliers. The solve time reported is IPOPT's wall time from the solver statistics.

Real time: the ECU gives a wall-clock budget per step (``set_time_budget``, real-time mode
only), and the NLP's functions run compiled (``controller.nlp_library``, same iterates, half
the step time); IPOPT stops at it (``max_wall_time``, status MAX_ITERATIONS) and the step falls back
to the shifted previous solution, the last one that converged, as on any solver failure.
The next step warm-starts from IPOPT's last iterate of the stopped solve, so that a solve
too slow from a cold start converges over the following steps.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Callable

import casadi as ca
import numpy as np

from controller.base import SolverStatus, VehicleSample
from controller.mpc_base import Plan, SteeringMpc
from controller.nlp_library import NlpLibraryError, compiled_solver
from controller.tuning import ControllerTuning, LongitudinalTuning, NmpcTuning

#: (state SX (3,) [vx, vy, yaw_rate], steer SX, drive_torque SX) -> derivatives (3,).
Dynamics = Callable[[Any, Any, Any], Any]

_LOG = logging.getLogger(__name__)

N_STATE = 6  # vx, vy, yaw_rate, X, Y, yaw

_IPOPT_STATUS = {
    "Solve_Succeeded": SolverStatus.SOLVED,
    "Solved_To_Acceptable_Level": SolverStatus.SOLVED_INACCURATE,
    "Maximum_Iterations_Exceeded": SolverStatus.MAX_ITERATIONS,
    "Maximum_CpuTime_Exceeded": SolverStatus.MAX_ITERATIONS,
    "Maximum_WallTime_Exceeded": SolverStatus.MAX_ITERATIONS,
    "Infeasible_Problem_Detected": SolverStatus.INFEASIBLE,
}


def _augmented_dynamics(dynamics: Dynamics) -> ca.Function:
    """Continuous dynamics of [vx, vy, yaw_rate, X, Y, yaw] (6,) for steer, torque."""
    state, steer, torque = ca.SX.sym("state", N_STATE), ca.SX.sym("steer"), ca.SX.sym("torque")
    planar = dynamics(state[0:3], steer, torque)
    if isinstance(planar, (list, tuple)):
        planar = ca.vertcat(*planar)
    vx, vy, yaw = state[0], state[1], state[5]
    pose_rate = ca.vertcat(vx * ca.cos(yaw) - vy * ca.sin(yaw), vx * ca.sin(yaw) + vy * ca.cos(yaw), state[2])
    return ca.Function("vehicle", [state, steer, torque], [ca.vertcat(planar, pose_rate)])


def rk4_step(derivatives: ca.Function, state: Any, steer: Any, torque: Any, ts: float) -> Any:
    """One classical Runge-Kutta step of ``ts``."""
    k1 = derivatives(state, steer, torque)
    k2 = derivatives(state + ts / 2 * k1, steer, torque)
    k3 = derivatives(state + ts / 2 * k2, steer, torque)
    k4 = derivatives(state + ts * k3, steer, torque)
    return state + ts / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


class Nmpc(SteeringMpc):
    """Nonlinear MPC (multiple shooting, RK4, IPOPT)."""

    name = "nmpc"

    def __init__(self, dynamics: Dynamics, tuning: NmpcTuning, longitudinal: LongitudinalTuning) -> None:
        self._build(dynamics, tuning)
        super().__init__(tuning, longitudinal)

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "Nmpc":
        """Build with ``models.single_track`` and its nominal parameters."""
        from models.single_track import CASADI_OPS, nominal_model_params, single_track_derivatives

        params = nominal_model_params()

        def dynamics(state: Any, steer: Any, torque: Any) -> Any:
            return single_track_derivatives(state, steer, torque, params, ops=CASADI_OPS)

        return cls(dynamics, tuning.nmpc, tuning.longitudinal)

    def _build(self, dynamics: Dynamics, tuning: NmpcTuning) -> None:
        n_pred, n_ctrl = tuning.prediction_horizon, tuning.control_horizon
        ts = 0.025
        derivatives = _augmented_dynamics(dynamics)
        states = ca.SX.sym("states", N_STATE, n_pred + 1)
        steer = ca.SX.sym("steer", n_ctrl)
        slack = ca.SX.sym("slack", 3)
        initial = ca.SX.sym("initial", N_STATE)
        reference = ca.SX.sym("reference", 3, n_pred)
        torque, previous_steer = ca.SX.sym("torque"), ca.SX.sym("previous_steer")
        # The scheduled weights (MpcTuning.weights_at at the measured vx): parameters, so
        # one NLP serves every speed.
        q_position, q_yaw, r_steer = ca.SX.sym("q_position"), ca.SX.sym("q_yaw"), ca.SX.sym("r_steer")

        constraints = [states[:, 0] - initial]
        cost = 0
        for i in range(n_pred):
            u = steer[min(i, n_ctrl - 1)]
            constraints.append(states[:, i + 1] - rk4_step(derivatives, states[:, i], u, torque, ts))
            error = states[3:6, i + 1] - reference[:, i]
            cost += q_position * (error[0] ** 2 + error[1] ** 2) + q_yaw * error[2] ** 2
        n_equal = N_STATE * (n_pred + 1)
        for i in range(1, n_pred + 1):  # eq. 21 softened: x - s <= x_max, x + s >= x_min
            constraints.append(states[0:3, i] - slack)
            constraints.append(states[0:3, i] + slack)
        increments = steer - ca.vertcat(previous_steer, steer[:-1])
        cost += r_steer * ca.sumsqr(steer) + tuning.p_steer_rate * ca.sumsqr(increments)
        cost += tuning.slack_l1 * ca.sum1(slack) + tuning.slack_l2 * ca.sumsqr(slack)

        variables = ca.vertcat(ca.vec(states), steer, slack)
        parameters = ca.vertcat(initial, ca.vec(reference), torque, previous_steer, q_position, q_yaw, r_steer)
        self._problem = {"x": variables, "p": parameters, "f": cost, "g": ca.vertcat(*constraints)}
        self._ipopt_limits = (tuning.ipopt_max_iter, tuning.ipopt_tol)
        self._solver = self._solver_with_budget(None)
        n_soft = 2 * 3 * n_pred
        lower_g = np.zeros(n_equal + n_soft)
        upper_g = np.zeros(n_equal + n_soft)
        soft_lower, soft_upper = lower_g[n_equal:].reshape(n_pred, 2, 3), upper_g[n_equal:].reshape(n_pred, 2, 3)
        soft_lower[:, 0, :], soft_upper[:, 0, :] = -np.inf, tuning.state_max
        soft_lower[:, 1, :], soft_upper[:, 1, :] = tuning.state_min, np.inf
        self._lower_g, self._upper_g = lower_g, upper_g
        n_states = N_STATE * (n_pred + 1)
        self._lower_x = np.concatenate((np.full(n_states, -np.inf), np.full(n_ctrl, -0.3), np.zeros(3)))
        self._upper_x = np.concatenate((np.full(n_states, np.inf), np.full(n_ctrl, 0.3), np.full(3, np.inf)))
        # Rollout for the start-up guess: the shooting states of a held steer.
        state0, steer0, torque0 = ca.SX.sym("x0", N_STATE), ca.SX.sym("u0"), ca.SX.sym("t0")
        trajectory = [state0]
        for _ in range(n_pred):
            trajectory.append(rk4_step(derivatives, trajectory[-1], steer0, torque0, ts))
        self._rollout = ca.Function("rollout", [state0, steer0, torque0], [ca.hcat(trajectory)])
        self._n_states = n_states
        self._warm: dict[str, np.ndarray] | None = None

    def _solver_with_budget(self, seconds: float | None, compiled: bool | None = None) -> Any:
        """IPOPT on the built NLP, stopped after ``seconds`` of wall clock (None: no limit).

        ``compiled`` (default: with a budget, i.e. in real time): the NLP's functions from a
        compiled library (``controller.nlp_library``: the same iterates, in about half the
        time); without a compiler CasADi's virtual machine evaluates them, as it does by
        default without a budget.
        """
        max_iter, tol = self._ipopt_limits
        ipopt = {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": tol, "warm_start_init_point": "yes"}
        options: dict[str, Any] = {"print_time": False, "record_time": True, "ipopt": ipopt}
        if seconds is not None:
            ipopt["max_wall_time"] = float(seconds)
        if compiled if compiled is not None else seconds is not None:
            try:
                return compiled_solver("nmpc", self._problem, options)
            except NlpLibraryError as error:
                _LOG.warning("NMPC's NLP not compiled (%s); evaluating it in CasADi's virtual machine, "
                             "about twice as slow", error)
        return ca.nlpsol("nmpc", "ipopt", self._problem, {**options, "expand": True})

    def set_time_budget(self, seconds: float | None, compiled: bool | None = None) -> None:
        """Stop IPOPT after ``seconds`` of wall clock per step (None: converge); real time only.
        ``compiled``: run the NLP compiled (default: exactly when there is a budget)."""
        if seconds is not None and not (math.isfinite(seconds) and seconds > 0.0):
            raise ValueError(f"NMPC time budget must be a positive number of seconds, got {seconds!r}")
        self._solver = self._solver_with_budget(seconds, compiled)

    def constraint_bounds(self, yaw_rate_bound: float) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of the NLP's constraints g, each (N_STATE (Np + 1) + 6 Np,): the
        tables', with the soft yaw-rate rows narrowed to +-``yaw_rate_bound`` (rad/s; the grip
        envelope's, ``controller.grip_envelope``) where that is tighter; inf: the tables'."""
        if not yaw_rate_bound < math.inf:
            return self._lower_g, self._upper_g
        n_pred, n_equal = self.tuning.prediction_horizon, self._n_states
        lower, upper = self._lower_g.copy(), self._upper_g.copy()
        # Row pairs per step: (x - s <= x_max, x + s >= x_min), each over [vx, vy, yaw_rate].
        upper[n_equal:].reshape(n_pred, 2, 3)[:, 0, 2] = min(self.tuning.state_max[2], yaw_rate_bound)
        lower[n_equal:].reshape(n_pred, 2, 3)[:, 1, 2] = max(self.tuning.state_min[2], -yaw_rate_bound)
        return lower, upper

    def reset(self) -> None:
        """Forget plans, warm starts and progress."""
        self._warm = None
        super().reset()

    def _plan(self, sample: VehicleSample, drive_torque: float, reference: np.ndarray) -> Plan:
        n_pred, n_ctrl = self.tuning.prediction_horizon, self.tuning.control_horizon
        initial = np.concatenate((sample.state(), sample.pose()))
        previous = self.previous_steer(sample)
        guess_steer = self.shifted_plan(sample)
        if self._warm is None:
            states_guess = np.asarray(self._rollout(initial, guess_steer[0], drive_torque))
            lam_x, lam_g = None, None
        else:
            states_guess = self._warm["states"].copy()
            states_guess[:, :-1] = states_guess[:, 1:]  # shift by one step
            # The measured yaw is wrapped: keep the guess on the same branch.
            states_guess[5] += 2.0 * math.pi * round((initial[5] - states_guess[5, 0]) / (2.0 * math.pi))
            states_guess[:, 0] = initial
            lam_x, lam_g = self._warm["lam_x"], self._warm["lam_g"]
        guess = np.concatenate((states_guess.ravel(order="F"), guess_steer, np.zeros(3)))
        weights = self.tuning.weights_at(sample.vx)
        parameters = np.concatenate((initial, reference.T.ravel(order="F"),
                                     [drive_torque, previous, weights.q_position, weights.q_yaw, weights.r_steer]))
        lower_g, upper_g = self.constraint_bounds(self.yaw_rate_bound)
        arguments = dict(x0=guess, p=parameters, lbx=self._lower_x, ubx=self._upper_x, lbg=lower_g, ubg=upper_g)
        if lam_x is not None:
            arguments.update(lam_x0=lam_x, lam_g0=lam_g)
        result = self._solver(**arguments)
        stats = self._solver.stats()
        status = _IPOPT_STATUS.get(stats.get("return_status", ""), SolverStatus.NUMERICAL_ERROR)
        solution = np.asarray(result["x"]).ravel()
        states = solution[:self._n_states].reshape(n_pred + 1, N_STATE).T  # (6, Np + 1)
        steer = solution[self._n_states:self._n_states + n_ctrl]
        slack = solution[self._n_states + n_ctrl:]
        converged = status in (SolverStatus.SOLVED, SolverStatus.SOLVED_INACCURATE)
        # A budget run out (real time) leaves IPOPT's last iterate for this very problem: the
        # next step goes on from it (shifted like a solution), so that a run of solves too
        # slow to converge from a cold start converges over a few steps instead of starting
        # cold again every step.
        interrupted = stats.get("return_status") == "Maximum_WallTime_Exceeded"
        if (converged or interrupted) and np.all(np.isfinite(solution)):
            self._warm = {"states": states, "lam_x": np.asarray(result["lam_x"]).ravel(),
                          "lam_g": np.asarray(result["lam_g"]).ravel()}
        else:
            self._warm = None
        return Plan(status=status, steer=steer, iterations=int(stats.get("iter_count", 0)),
                    solve_time_s=float(stats.get("t_wall_total", 0.0)), cost=float(result["f"]),
                    predicted_pose=states[3:6, 1:].T.copy(), predicted_state=states[0:3, 1:].T.copy(),
                    slack_max=float(np.max(slack)))

"""The condensed steering QP of eq. 15 solved by OSQP (shared by LMPC, DKMPC, ESO-DKMPC).

Decision variables v = [U (Nc steer angles), s (3 slacks, one per state of eq. 21)].
The pose over the horizon is linearised in U (real-time iteration, see pose_kinematics),
the dynamic states are affine in U, so eq. 15 becomes

    min  sum_i ||pose_i(U) - ref_i||^2_Q + r ||U||^2 + p ||D U - d||^2 + l1 1's + l2 ||s||^2
    s.t. -steer_limit <= U <= steer_limit                          (eq. 22)
         s >= 0
         x_min - s <= state_i(U) <= x_max + s,  i in soft steps     (eq. 21, soft)

D U - d are the increments U_j - U_{j-1} with U_{-1} = the previous command. The slack
makes the QP always feasible; with the L1 weight large it is an exact penalty: the slack
is zero whenever the hard constraints can be met.

Soft rows (:data:`SOFT_STATES`, :data:`SOFT_STEP_STRIDE`, :func:`soft_state_rows`): eq. 21
is checked for vy and the yaw rate at every 3rd prediction step and at the last (steps 3,
6, ..., 30 at Np 30): 20 state rows, 40 constraint rows, instead of all three states at
every step (90 state rows, 180 constraint rows). vx has no soft rows, so its slack s[0]
has only its bound row s[0] >= 0 and is always 0 (kept so that the decision vector and
the C core's layout stay the same for every selection). The states between the soft steps
are not bounded: with a bound that is active near the start of the horizon the predicted
state at steps 1 and 2 can exceed it (tests/test_controller_qp.py prints by how much).

The sparsity pattern is built once. P's dense Nc x Nc upper triangle is written straight
into a preallocated data array (a view), A's state-gain block through a fixed gather
index; both are passed to ``OSQP.update(Px=..., Ax=...)`` each step. A holds only the
gain's causal entries: the state at step i depends on U_c only for c < i (U_c is the input
of step c, the last one held from step Nc - 1 on), so the entries with c >= i are zero by
construction and are left out of the pattern (14 of the 160 entries of the 20 soft state
rows at Np 30, Nc 8: a smaller KKT matrix to factor every step, the same QP).

OSQP runs unscaled (``scaling=0``, :data:`OSQP_SCALING_ITERATIONS`): P and A change every
step, and with scaling on OSQP re-runs its Ruiz equilibration on every update, about 40 %
of the C firmware's step (docs/firmware.md, Timing). The firmware's solver is generated
from this object (firmware/tools/generate.py), so both implementations change together.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sparse

from controller.base import STEER_LIMIT_RAD, SolverStatus
from controller.tuning import QpMpcTuning

N_SOFT_STATES = 3  # vx, vy, yaw_rate: one slack each (the decision vector's last 3 entries)
#: The states of eq. 21 that get soft rows, as indices into [vx, vy, yaw_rate]. vx is left
#: out: the steering hardly moves it, the longitudinal controller owns it, and its bounds
#: [0, 40] m/s are never near. The firmware's layout is generated from this
#: (firmware/tools/generate.py: ECU_SOFT_STATE_MASK).
SOFT_STATES = (1, 2)
#: Soft rows at the prediction steps SOFT_STEP_STRIDE, 2 SOFT_STEP_STRIDE, ... and always at
#: the last step Np: eq. 21's limits move over tens of steps, so every 3rd step holds them.
#: Measured with "no vx, every 3rd step" against all three states at every step (issue 18,
#: make bench's 540 dlc_high_mu samples, the C step's own time, p50 us): ESO-DKMPC 67 -> 38,
#: DKMPC 64.9 -> 36.7, LMPC 49.1 -> 23.5; ESO-DKMPC's p99 of each sample's fastest of 8
#: repeats 68 -> 39 us. Tuning set (studies/tuning_set.py): e_Y RMSE within 0.02 mm for
#: ESO-DKMPC and DKMPC, 0.1 mm for LMPC; every run completes. (ECU_SOFT_STRIDE in C.)
SOFT_STEP_STRIDE = 3
#: OSQP's Ruiz scaling iterations (its default is 10). 0: none, so an update of P and A
#: is a copy and a refactorization. Measured on the tuning set (studies/tuning_set.py,
#: docs/firmware.md): e_Y objective of ESO-DKMPC / DKMPC / LMPC within 0.12 mm of the
#: scaled solver's (as close as tightening eps from 1e-3 to 1e-4 moves it), every QP
#: SOLVED, iterations per solve about the same (mean 7.0 vs 7.4 for ESO-DKMPC).
OSQP_SCALING_ITERATIONS = 0
#: OSQP's duality-gap termination test (on by default since OSQP 1.0) off: the solve stops
#: on the primal and dual residuals alone (eps_abs, eps_rel), as OSQP 0.6 did. The gap test
#: was what kept 5 % of make bench's steps at 10 iterations instead of 5 (the step's p99).
#: Measured on the tuning set: mean iterations 7.0 -> 5.4 (ESO-DKMPC), 6.9 -> 5.7 (LMPC),
#: e_Y objective within 0.11 mm (the eps 1e-3 -> 1e-4 yardstick: 0.10 mm), every QP SOLVED.
OSQP_CHECK_DUALITY_GAP = False

_STATUS = {
    osqp.SolverStatus.OSQP_SOLVED: SolverStatus.SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE: SolverStatus.SOLVED_INACCURATE,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED: SolverStatus.MAX_ITERATIONS,
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE: SolverStatus.INFEASIBLE,
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE: SolverStatus.INFEASIBLE,
    osqp.SolverStatus.OSQP_DUAL_INFEASIBLE: SolverStatus.INFEASIBLE,
    osqp.SolverStatus.OSQP_DUAL_INFEASIBLE_INACCURATE: SolverStatus.INFEASIBLE,
}


def soft_steps(n_pred: int) -> np.ndarray:
    """Indices i (0-based, the state at step i + 1) of the prediction steps with soft rows:
    every :data:`SOFT_STEP_STRIDE`-th step and the last one, ascending, (n_steps,)."""
    steps = np.arange(n_pred)
    return steps[((steps + 1) % SOFT_STEP_STRIDE == 0) | (steps == n_pred - 1)]


def soft_state_rows(n_pred: int) -> np.ndarray:
    """The soft-constrained entries of the flattened (Np * 3,) predicted states, index
    ``3 i + k`` for step index i of :func:`soft_steps` and state k of :data:`SOFT_STATES`,
    step-major (the order of A's soft rows), (n_steps * len(SOFT_STATES),)."""
    return (N_SOFT_STATES * soft_steps(n_pred)[:, None] + np.array(SOFT_STATES)[None, :]).ravel()


@dataclass(frozen=True)
class QpSolution:
    """One QP solve: ``steer`` (Nc,), ``slack`` (3,) for [vx, vy, yaw_rate] (the vx slack has
    no soft rows, :data:`SOFT_STATES`, and is 0); times from OSQP."""

    status: SolverStatus
    steer: np.ndarray
    slack: np.ndarray
    iterations: int
    solve_time_s: float
    cost: float


class SteeringQp:
    """OSQP problem of fixed size and sparsity for horizons (Np, Nc); updated in place."""

    def __init__(self, tuning: QpMpcTuning, steer_limit: float = STEER_LIMIT_RAD) -> None:
        n_pred, n_ctrl = tuning.prediction_horizon, tuning.control_horizon
        self.n_pred, self.n_ctrl = n_pred, n_ctrl
        self.tuning = tuning
        # The flattened state entries with soft rows (step-major), (n_rows,).
        self._soft_rows = soft_state_rows(n_pred)
        n_soft_rows = 2 * self._soft_rows.size
        self._n_var = n_ctrl + N_SOFT_STATES
        n_con = n_ctrl + N_SOFT_STATES + n_soft_rows
        # Pose weight per flattened (step, [X, Y, yaw]) entry.
        self._pose_weight = np.tile([tuning.q_position, tuning.q_position, tuning.q_yaw], n_pred)
        # Increment operator: (D U)_j = U_j - U_{j-1}; U_{-1} enters through the linear term.
        difference = np.eye(n_ctrl) - np.eye(n_ctrl, k=-1)
        self._fixed_hessian = tuning.r_steer * np.eye(n_ctrl) + tuning.p_steer_rate * difference.T @ difference

        # P: dense upper triangle of the U block, then the slack diagonal (CSC, column order).
        rows, cols = [], []
        for j in range(n_ctrl):
            rows.extend(range(j + 1))
            cols.extend([j] * (j + 1))
        self._triu_rows, self._triu_cols = np.array(rows), np.array(cols)
        p_indptr = np.concatenate(([0], np.cumsum(np.arange(1, n_ctrl + 1)),
                                   len(rows) + np.arange(1, N_SOFT_STATES + 1)))
        p_indices = np.concatenate((self._triu_rows, n_ctrl + np.arange(N_SOFT_STATES)))
        self._p_data = np.zeros(p_indices.size)
        self._p_data[len(rows):] = 2.0 * tuning.slack_l2
        self._p_upper = self._p_data[:len(rows)]  # view: the U block's values

        # A, column by column. U column j: its bound row, then the soft rows of the steps
        # i > j (the causal gain entries; the flattened state rows from 3 j on), both sides.
        # Soft rows: (r * 2 + side) for the r-th entry of soft_state_rows, side 0 = upper
        # (-s), 1 = lower (+s).
        soft_first = n_ctrl + N_SOFT_STATES
        self._soft_first = soft_first
        position = np.arange(self._soft_rows.size)  # r
        indices, indptr = [], [0]
        gain_source, gain_slot = [], []  # state_gain.ravel() index -> A data slot
        for j in range(n_ctrl):
            causal = self._soft_rows >= N_SOFT_STATES * min(j, n_pred)
            state_rows, r = self._soft_rows[causal], position[causal]
            indices.append(np.concatenate(([j], soft_first + np.stack((2 * r, 2 * r + 1), 1).ravel())))
            gain_source.append(np.repeat(state_rows * n_ctrl + j, 2))
            gain_slot.append(indptr[-1] + 1 + np.arange(2 * state_rows.size))
            indptr.append(indptr[-1] + 1 + 2 * state_rows.size)
        u_nnz = indptr[-1]
        self._gain_source, self._gain_slot = np.concatenate(gain_source), np.concatenate(gain_slot)
        slack_signs = []
        for k in range(N_SOFT_STATES):  # slack column k: its bound row, then state k's soft rows
            soft_rows = soft_first + 2 * position[self._soft_rows % N_SOFT_STATES == k]
            indices.append(np.concatenate(([n_ctrl + k], np.stack((soft_rows, soft_rows + 1), 1).ravel())))
            indptr.append(indptr[-1] + 1 + 2 * soft_rows.size)
            slack_signs.append(np.concatenate(([1.0], np.tile([-1.0, 1.0], soft_rows.size))))
        a_indices = np.concatenate(indices)
        self._a_data = np.concatenate((np.zeros(u_nnz), *slack_signs))
        self._a_data[indptr[:n_ctrl]] = 1.0  # the steer bound rows

        self._q = np.zeros(self._n_var)
        self._q[n_ctrl:] = tuning.slack_l1
        self._lower = np.full(n_con, -np.inf)
        self._upper = np.full(n_con, np.inf)
        self._lower[:n_ctrl], self._upper[:n_ctrl] = -steer_limit, steer_limit
        self._lower[n_ctrl:soft_first] = 0.0
        self._state_min = np.tile(tuning.state_min, n_pred)[self._soft_rows]
        self._state_max = np.tile(tuning.state_max, n_pred)[self._soft_rows]
        self._soft_upper = self._upper[soft_first::2]  # views, (n_rows,)
        self._soft_lower = self._lower[soft_first + 1::2]
        self._soft_upper[:] = self._state_max
        self._soft_lower[:] = self._state_min

        self._p_upper[:] = self._fixed_hessian[self._triu_rows, self._triu_cols]
        hessian = sparse.csc_matrix((self._p_data.copy(), p_indices, p_indptr),
                                    shape=(self._n_var, self._n_var))
        constraints = sparse.csc_matrix((self._a_data.copy(), a_indices, np.array(indptr)),
                                        shape=(n_con, self._n_var))
        self._solver = osqp.OSQP()
        self._solver.setup(hessian, self._q.copy(), constraints, self._lower.copy(), self._upper.copy(),
                           warm_starting=True, polishing=False, verbose=False,
                           eps_abs=tuning.osqp_eps_abs, eps_rel=tuning.osqp_eps_rel,
                           max_iter=tuning.osqp_max_iter, check_termination=5,
                           adaptive_rho_interval=25, scaling=OSQP_SCALING_ITERATIONS,
                           check_dualgap=OSQP_CHECK_DUALITY_GAP)
        self._warm = np.zeros(self._n_var)
        # Dual start: with the state constraints inactive (the usual case) the multipliers of
        # s >= 0 equal the L1 weight. Starting them there instead of at 0 saves the hundreds
        # of ADMM iterations it takes to build a large dual up from zero.
        self._initial_dual = np.zeros(n_con)
        self._initial_dual[n_ctrl:soft_first] = -tuning.slack_l1
        self._solver.warm_start(x=self._warm, y=self._initial_dual)
        self._constraints_were_active = False

    def solve(self, pose_jacobian: np.ndarray, pose_offset: np.ndarray, previous_steer: float,
              state_gain: np.ndarray, state_free: np.ndarray, warm_steer: np.ndarray) -> QpSolution:
        """Update the data and solve.

        pose_jacobian (Np, 3, Nc), pose_offset (Np, 3): linearised pose minus reference is
        ``pose_jacobian @ U + pose_offset``. state_gain (Np, 3, Nc) and state_free (Np, 3):
        the states at steps 1..Np are ``state_gain @ U + state_free``; the entries
        ``state_gain[k, :, c]`` with c > k are zero for every causal prediction and are not
        read (see the module docstring). warm_steer (Nc,).
        """
        n_ctrl = self.n_ctrl
        jac = pose_jacobian.reshape(-1, n_ctrl)
        offset = pose_offset.ravel()
        weighted_jac = jac * self._pose_weight[:, None]
        hessian = jac.T @ weighted_jac + self._fixed_hessian  # (Nc, Nc), half of OSQP's P
        self._p_upper[:] = 2.0 * hessian[self._triu_rows, self._triu_cols]
        self._q[:n_ctrl] = 2.0 * (offset @ weighted_jac)
        self._q[0] -= 2.0 * self.tuning.p_steer_rate * previous_steer

        self._a_data[self._gain_slot] = state_gain.reshape(-1)[self._gain_source]
        free = state_free.ravel()[self._soft_rows]
        self._soft_upper[:] = self._state_max - free
        self._soft_lower[:] = self._state_min - free

        solver = self._solver
        solver.update(q=self._q, l=self._lower, u=self._upper, Px=self._p_data, Ax=self._a_data)
        self._warm[:n_ctrl] = warm_steer
        if self._constraints_were_active:
            solver.warm_start(x=self._warm)  # keep the multipliers of the active set
        else:
            solver.warm_start(x=self._warm, y=self._initial_dual)
        result = solver.solve(raise_error=False)
        info = result.info
        status = _STATUS.get(info.status_val, SolverStatus.NUMERICAL_ERROR)
        solution = np.array(result.x, dtype=float)
        if status in (SolverStatus.SOLVED, SolverStatus.SOLVED_INACCURATE):
            # Measured: restarting the multipliers at the inactive-constraint values halves the
            # iterations while no state constraint is active, and doubles them while one is.
            self._constraints_were_active = bool(np.max(np.abs(result.y[self._soft_first:])) > 1.0)
        else:
            # Do not start the next solve from the failed iterate's multipliers.
            solver.warm_start(y=self._initial_dual)
            self._constraints_were_active = False
        constant = float(offset @ (offset * self._pose_weight)) + self.tuning.p_steer_rate * previous_steer ** 2
        return QpSolution(status=status, steer=solution[:n_ctrl], slack=solution[n_ctrl:],
                          iterations=int(info.iter), solve_time_s=float(info.run_time),
                          cost=float(info.obj_val) + constant)

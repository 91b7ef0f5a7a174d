"""Base of the MPCs solved as one OSQP QP per step (LMPC, DKMPC, ESO-DKMPC).

A subclass gives the dynamic states over the horizon as an affine function of the steer
sequence U (Nc,), the drive torque being fixed by the P controller (eq. 22's torque rows):
states[i] = free[i] + gain[i] @ U, i = 0..Np (step 0 is the measurement). This base
linearises the pose of eq. 20 about the shifted previous solution (real-time iteration:
one QP per step, no re-linearisation within the step) and solves ``SteeringQp``, with the
yaw-rate rows of eq. 21 narrowed by the grip envelope's bound of the step
(``SteeringMpc.yaw_rate_bound``, ``controller.grip_envelope``).
"""
from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import replace

import numpy as np

from controller.base import SolverStatus, VehicleSample
from controller.delay_compensation import DelayWindow, delay_window, pose_after, total_delay
from controller.mpc_base import Plan, SteeringMpc
from controller.pose_kinematics import linearise_pose
from controller.steering_qp import SteeringQp
from controller.tuning import LongitudinalTuning, QpMpcTuning
from models.measurement import wrap_angle


def held_input_map(n_pred: int, n_ctrl: int) -> np.ndarray:
    """Held-input map (Np, Nc): the input at step i is U[min(i, Nc - 1)] (eq. 15, i >= Nc)."""
    hold = np.zeros((n_pred, n_ctrl))
    hold[np.arange(n_pred), np.minimum(np.arange(n_pred), n_ctrl - 1)] = 1.0
    return hold


class QpSteeringMpc(SteeringMpc):
    """Steering MPC on an affine state prediction, one sparse OSQP QP per step."""

    def __init__(self, tuning: QpMpcTuning, longitudinal: LongitudinalTuning) -> None:
        self.qp = SteeringQp(tuning)
        self.hold = held_input_map(tuning.prediction_horizon, tuning.control_horizon)
        super().__init__(tuning, longitudinal)

    @abstractmethod
    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """Affine state prediction: free (Np + 1, 3) and gain (Np + 1, 3, Nc) for steps 0..Np."""

    @abstractmethod
    def shift_start(self, free: np.ndarray, window: DelayWindow) -> np.ndarray:
        """The free response (Np + 1, 3) of the last ``predict_states`` moved to start at the
        end of ``window``: the model's own start state predicted forward over it with the
        commands in flight (``controller.delay_compensation.forward_state``)."""

    def _prepare(self, sample: VehicleSample, drive_torque: float) -> VehicleSample:
        """With delay compensation on: predict once from the measured sample, move the
        prediction's start over the delay window and return the sample at the window's end
        (pose and [vx, vy, yaw_rate] as the model predicts them), which the reference, the
        weights and the pose rows then use; the observer keeps the measurement."""
        self._prepared: tuple[np.ndarray, np.ndarray] | None = None
        delay = total_delay(self.tuning.delay_compensation_s, sample.sample_age_s)
        if delay <= 0.0:
            return sample
        free, gain = self.predict_states(sample, drive_torque)
        if not (math.isfinite(free.sum()) and math.isfinite(gain.sum())):
            self._prepared = (free, gain)  # _plan falls back on it
            return sample
        window = delay_window(delay, self.ts, list(self._command_history) or [self.previous_steer(sample)])
        n_ctrl, last = self.tuning.control_horizon, window.whole_steps
        in_flight = window.inputs[np.minimum(np.arange(n_ctrl), last)]  # U of the window's grid steps
        states = free[:last + 2] + gain[:last + 2] @ in_flight  # (whole + 2, 3), steps 0..whole + 1
        pose = pose_after(sample.pose(), states[:last + 1], self.ts, window, self.tuning.pose_heading_advance)
        moved = states[last] + window.fraction * (states[last + 1] - states[last])
        self._prepared = (self.shift_start(free, window), gain)
        return replace(sample, vx=float(moved[0]), vy=float(moved[1]), yaw_rate=float(moved[2]),
                       x=float(pose[0]), y=float(pose[1]), yaw=float(wrap_angle(pose[2])))

    def _plan(self, sample: VehicleSample, drive_torque: float, reference: np.ndarray) -> Plan:
        prepared = getattr(self, "_prepared", None)
        self._prepared = None
        free, gain = prepared if prepared is not None else self.predict_states(sample, drive_torque)
        nominal = self.shifted_plan(sample)
        n_pred = self.tuning.prediction_horizon
        empty = np.zeros((0, 3))
        # A sum is finite iff every entry is (or it overflowed: rejected too, rightly).
        if not (math.isfinite(free.sum()) and math.isfinite(gain.sum())):
            return Plan(SolverStatus.NUMERICAL_ERROR, nominal, 0, 0.0, float("nan"), empty, empty)
        nominal_states = free + gain @ nominal  # (Np + 1, 3)
        pose_nominal, jacobian = linearise_pose(sample.pose(), nominal_states[:n_pred], gain[:n_pred], self.ts,
                                                 self.tuning.pose_heading_advance)
        pose_offset = pose_nominal - jacobian @ nominal - reference
        solution = self.qp.solve(jacobian, pose_offset, self.previous_steer(sample), gain[1:], free[1:], nominal,
                                 weights=self.tuning.weights_at(sample.vx), yaw_rate_bound=self.yaw_rate_bound)
        steer = solution.steer
        return Plan(status=solution.status, steer=steer, iterations=solution.iterations,
                    solve_time_s=solution.solve_time_s, cost=solution.cost,
                    predicted_pose=pose_nominal + jacobian @ (steer - nominal),
                    predicted_state=free[1:] + gain[1:] @ steer,
                    slack_max=float(np.max(solution.slack)))

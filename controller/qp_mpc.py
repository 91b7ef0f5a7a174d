"""Base of the MPCs solved as one OSQP QP per step (LMPC, DKMPC, ESO-DKMPC).

A subclass gives the dynamic states over the horizon as an affine function of the steer
sequence U (Nc,), the drive torque being fixed by the P controller (eq. 22's torque rows):
states[i] = free[i] + gain[i] @ U, i = 0..Np (step 0 is the measurement). This base
linearises the pose of eq. 20 about the shifted previous solution (real-time iteration:
one QP per step, no re-linearisation within the step) and solves ``SteeringQp``.
"""
from __future__ import annotations

import math
from abc import abstractmethod

import numpy as np

from controller.base import SolverStatus, VehicleSample
from controller.mpc_base import Plan, SteeringMpc
from controller.pose_kinematics import linearise_pose
from controller.steering_qp import SteeringQp
from controller.tuning import LongitudinalTuning, QpMpcTuning


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

    def _plan(self, sample: VehicleSample, drive_torque: float, reference: np.ndarray) -> Plan:
        free, gain = self.predict_states(sample, drive_torque)
        nominal = self.shifted_plan(sample)
        n_pred = self.tuning.prediction_horizon
        empty = np.zeros((0, 3))
        # A sum is finite iff every entry is (or it overflowed: rejected too, rightly).
        if not (math.isfinite(free.sum()) and math.isfinite(gain.sum())):
            return Plan(SolverStatus.NUMERICAL_ERROR, nominal, 0, 0.0, float("nan"), empty, empty)
        nominal_states = free + gain @ nominal  # (Np + 1, 3)
        pose_nominal, jacobian = linearise_pose(sample.pose(), nominal_states[:n_pred], gain[:n_pred], self.ts)
        pose_offset = pose_nominal - jacobian @ nominal - reference
        solution = self.qp.solve(jacobian, pose_offset, self.previous_steer(sample), gain[1:], free[1:], nominal,
                                 weights=self.tuning.weights_at(sample.vx))
        steer = solution.steer
        return Plan(status=solution.status, steer=steer, iterations=solution.iterations,
                    solve_time_s=solution.solve_time_s, cost=solution.cost,
                    predicted_pose=pose_nominal + jacobian @ (steer - nominal),
                    predicted_state=free[1:] + gain[1:] @ steer,
                    slack_max=float(np.max(solution.slack)))

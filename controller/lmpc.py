"""LMPC: steering MPC on the linear 2-DoF bicycle model (paper Section IV-B 1)).

Lateral state [vy, yaw_rate], input the front wheel angle, discretised at Ts for the
measured vx (held over the horizon, as is the torque: the P controller owns vx).
Same pose kinematics, cost, constraints and QP as the Koopman MPCs.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from controller.base import VehicleSample
from controller.delay_compensation import DelayWindow, forward_state
from controller.qp_mpc import QpSteeringMpc
from controller.tuning import ControllerTuning, LongitudinalTuning, QpMpcTuning

#: The bicycle model's 1/vx terms blow up near standstill; below this speed (m/s) the
#: model is evaluated at this speed (the path reference then barely moves anyway).
MIN_MODEL_SPEED = 1.0
#: Speed resolution of the cached discretisations (m/s). The discrete matrices change by
#: far less than the model's own error over 0.01 m/s, and caching keeps the matrix
#: exponential (tens of microseconds, but BLAS-threaded and slow on a loaded machine) out
#: of most steps.
SPEED_QUANTUM = 0.01
_CACHE_SIZE = 4096


class DiscreteLateralModel(Protocol):
    """What LMPC needs of ``models.bicycle.LinearBicycle``."""

    def discrete_matrices(self, vx: float, ts: float) -> tuple[np.ndarray, np.ndarray]:
        """(A (2, 2), B (2, 1)) of x+ = A x + B steer, x = [vy, yaw_rate]."""


class Lmpc(QpSteeringMpc):
    """Linear MPC on the 2-DoF bicycle model."""

    name = "lmpc"

    def __init__(self, bicycle: DiscreteLateralModel, tuning: QpMpcTuning,
                 longitudinal: LongitudinalTuning) -> None:
        self.bicycle = bicycle
        super().__init__(tuning, longitudinal)
        n_pred = tuning.prediction_horizon
        steps = np.arange(1, n_pred + 1)[:, None]
        inputs = np.arange(n_pred)[None, :]
        # Markov index of input j seen at step i: i - 1 - j for j < i, else the zero row Np.
        self._markov_index = np.where(inputs < steps, steps - 1 - inputs, n_pred)  # (Np, Np)
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "Lmpc":
        """Build with the nominal bicycle model of ``models.bicycle``."""
        from models.bicycle import LinearBicycle

        return cls(LinearBicycle(), tuning.lmpc, tuning.longitudinal)

    def _prediction_maps(self, vx: float) -> tuple[np.ndarray, np.ndarray]:
        """Lateral free-response map (Np + 1, 2, 2) = A^i and steer gain (Np + 1, 3, Nc) at vx
        rounded to SPEED_QUANTUM, cached (so a step is two small products at steady speed)."""
        key = round(max(vx, MIN_MODEL_SPEED) / SPEED_QUANTUM)
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        n_pred = self.tuning.prediction_horizon
        a, b = self.bicycle.discrete_matrices(key * SPEED_QUANTUM, self.ts)
        b = np.asarray(b, dtype=float).reshape(2)
        powers = np.empty((n_pred + 1, 2, 2))
        powers[0] = np.eye(2)
        markov = np.zeros((n_pred + 1, 2))  # A^k b, k = 0..Np-1, then a zero row
        for k in range(n_pred):
            markov[k] = powers[k] @ b
            powers[k + 1] = a @ powers[k]
        gain = np.zeros((n_pred + 1, 3, self.tuning.control_horizon))  # vx row stays 0
        gain[1:, 1:, :] = np.einsum("ijs,jc->isc", markov[self._markov_index], self.hold)
        if len(self._cache) >= _CACHE_SIZE:
            self._cache.clear()
        self._cache[key] = (powers, gain)
        return powers, gain

    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """free (Np + 1, 3), gain (Np + 1, 3, Nc); vx stays the measured value."""
        powers, gain = self._prediction_maps(sample.vx)
        lateral = np.array([sample.vy, sample.yaw_rate])
        self._start = (powers, gain, lateral)  # for shift_start
        free = np.empty((powers.shape[0], 3))
        free[:, 0] = sample.vx
        free[:, 1:] = powers @ lateral
        return free, gain

    def shift_start(self, free: np.ndarray, window: DelayWindow) -> np.ndarray:
        """[vy, yaw_rate] moved over ``window`` by the bicycle at this step's speed,
        x+ = A x + b steer (A = A^1, b = the step-1 steer gain of the cached maps), and the
        free response (Np + 1, 3) from there: free + A^i (x_d - x_k) on the lateral rows."""
        powers, gain, lateral = self._start
        transition, steer_column = powers[1], gain[1, 1:, 0]
        moved = forward_state(lambda x, steer: transition @ x + steer_column * steer, lateral, window)
        shifted = free.copy()
        shifted[:, 1:] += powers @ (moved - lateral)
        return shifted

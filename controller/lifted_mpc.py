"""The Koopman MPCs' prediction (DKMPC, ESO-DKMPC): eq. 15 in the lifted space.

z[i+1] = A z[i] + B [T, delta_i] + offset + w_hat, with T the P controller's torque and
w_hat the disturbance estimate held over the horizon (zero for DKMPC). Because A, B and
the hold structure are constant, the steer-to-state map is computed once at build time:

    states[i] = C_P A^i z0 + C_P S_i (B_T T + offset + w_hat) + gain[i] @ U,
    S_i = sum_{j<i} A^j,   gain[i] = C_P sum_{j<i} A^{i-1-j} B_delta hold[j]

so a step costs two small matrix-vector products besides the lift and the QP.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controller.base import VehicleSample
from controller.qp_mpc import QpSteeringMpc
from controller.tuning import LongitudinalTuning, QpMpcTuning

if TYPE_CHECKING:
    from models.koopman import KoopmanModel

TORQUE, STEER = 0, 1  # input order [torque, steer]


class LiftedMpc(QpSteeringMpc):
    """Steering MPC on a ``KoopmanModel`` (A, B, offset, C_P, lift). DKMPC as is."""

    def __init__(self, model: "KoopmanModel", tuning: QpMpcTuning, longitudinal: LongitudinalTuning) -> None:
        self.model = model
        super().__init__(tuning, longitudinal)
        n_pred, n_z = tuning.prediction_horizon, model.n_z
        powers = np.empty((n_pred + 1, n_z, n_z))
        sums = np.empty((n_pred + 1, n_z, n_z))
        powers[0], sums[0] = np.eye(n_z), np.zeros((n_z, n_z))
        for i in range(n_pred):
            powers[i + 1] = model.A @ powers[i]
            sums[i + 1] = sums[i] + powers[i]
        # Lifted response to one steer input applied at step j, seen at step i > j.
        impulse = powers[:n_pred] @ model.B[:, STEER]  # (Np, n_z): A^k B_delta
        lifted_gain = np.zeros((n_pred + 1, n_z, tuning.control_horizon))
        for i in range(1, n_pred + 1):
            lifted_gain[i] = impulse[i - 1::-1].T @ self.hold[:i]  # sum_j A^{i-1-j} B_d hold[j]
        self._free_from_lifted = model.C_P @ powers  # (Np + 1, n_x, n_z)
        self._free_from_drift = model.C_P @ sums  # (Np + 1, n_x, n_z)
        self._gain = model.C_P @ lifted_gain  # (Np + 1, n_x, Nc)
        self.lifted_state: np.ndarray | None = None  # z_k of the last step

    def disturbance(self, lifted_state: np.ndarray) -> np.ndarray:
        """w_hat (n_z,) held over the horizon; zero for DKMPC."""
        return np.zeros(self.model.n_z)

    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """States [vx, vy, yaw_rate] at steps 0..Np: free (Np + 1, 3), gain (Np + 1, 3, Nc)."""
        lifted = self.model.lift(sample.state())
        self.lifted_state = lifted
        drift = self.model.B[:, TORQUE] * drive_torque + self.model.offset + self.disturbance(lifted)
        free = self._free_from_lifted @ lifted + self._free_from_drift @ drift
        return free, self._gain

"""The Koopman MPCs' prediction (DKMPC, ESO-DKMPC): eq. 15 in the lifted space.

z[i+1] = A z[i] + B [T, delta_i] + offset + w_i, with T the P controller's torque and
w_i the disturbance estimate at prediction step i (zero for DKMPC; ESO-DKMPC adds it
through ``disturbance_response``). Because A, B and the hold structure are constant, the
steer-to-state map is computed once at build time:

    states[i] = C_P A^i z0 + C_P S_i (B_T T + offset) + [disturbance part] + gain[i] @ U,
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


def decayed_sums(A: np.ndarray, n_pred: int, decay: float) -> np.ndarray:
    """D_i = sum_{j<i} A^(i-1-j) decay^j for i = 0..Np, shape (Np + 1, n_z, n_z).

    The lifted state at step i gained from an additive input decay^j w at every step j < i
    is D_i w; decay = 1 gives S_i = sum_{j<i} A^j (a constant input).
    """
    n_z = A.shape[0]
    sums = np.zeros((n_pred + 1, n_z, n_z))
    for i in range(n_pred):
        sums[i + 1] = A @ sums[i] + decay ** i * np.eye(n_z)  # D_{i+1} = A D_i + decay^i I
    return sums


class LiftedMpc(QpSteeringMpc):
    """Steering MPC on a ``KoopmanModel`` (A, B, offset, C_P, lift). DKMPC as is."""

    def __init__(self, model: "KoopmanModel", tuning: QpMpcTuning, longitudinal: LongitudinalTuning) -> None:
        self.model = model
        super().__init__(tuning, longitudinal)
        n_pred, n_z = tuning.prediction_horizon, model.n_z
        powers = np.empty((n_pred + 1, n_z, n_z))
        powers[0] = np.eye(n_z)
        for i in range(n_pred):
            powers[i + 1] = model.A @ powers[i]
        sums = decayed_sums(model.A, n_pred, 1.0)
        # Lifted response to one steer input applied at step j, seen at step i > j.
        impulse = powers[:n_pred] @ model.B[:, STEER]  # (Np, n_z): A^k B_delta
        lifted_gain = np.zeros((n_pred + 1, n_z, tuning.control_horizon))
        for i in range(1, n_pred + 1):
            lifted_gain[i] = impulse[i - 1::-1].T @ self.hold[:i]  # sum_j A^{i-1-j} B_d hold[j]
        self._free_from_lifted = model.C_P @ powers  # (Np + 1, n_x, n_z)
        self._free_from_drift = model.C_P @ sums  # (Np + 1, n_x, n_z)
        self._gain = model.C_P @ lifted_gain  # (Np + 1, n_x, Nc)
        self.lifted_state: np.ndarray | None = None  # z_k of the last step

    def disturbance_response(self, lifted_state: np.ndarray) -> np.ndarray | float:
        """The disturbance estimate's share of the states at steps 0..Np, (Np + 1, 3); 0 for DKMPC."""
        return 0.0

    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """States [vx, vy, yaw_rate] at steps 0..Np: free (Np + 1, 3), gain (Np + 1, 3, Nc)."""
        lifted = self.model.lift(sample.state())
        self.lifted_state = lifted
        drift = self.model.B[:, TORQUE] * drive_torque + self.model.offset
        free = (self._free_from_lifted @ lifted + self._free_from_drift @ drift
                + self.disturbance_response(lifted))
        return free, self._gain

"""The Koopman MPCs' prediction (DKMPC, ESO-DKMPC): eq. 15 in the lifted space.

z[i+1] = A z[i] + B_k [T, delta_i] + offset + w_i, with T the P controller's torque and
w_i the disturbance estimate at prediction step i (zero for DKMPC; ESO-DKMPC adds it
through ``disturbance_response``). B_k = B for the paper's linear model; for a bilinear
model B_k = B(z_k) = B + [N_T z_k, N_delta z_k], the input matrix at the measured lifted
state, held over the horizon so the prediction stays linear in U and the MPC a QP:

    states[i] = C_P A^i z0 + C_P S_i (B_T T + offset) + [disturbance part] + gain[i] @ U,
    S_i = sum_{j<i} A^j,   gain[i] = C_P sum_{j<i} A^{i-1-j} B_delta hold[j]

gain[i] is linear in B_delta: gain = G @ B_delta with G (Np + 1, 3, Nc, n_z) built once, so
a step costs a few small matrix-vector products besides the lift and the QP.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from controller.base import VehicleSample
from controller.delay_compensation import DelayWindow, forward_state
from controller.errors import ControllerError
from controller.qp_mpc import QpSteeringMpc, held_input_map
from controller.tuning import LongitudinalTuning, QpMpcTuning

if TYPE_CHECKING:
    from models.koopman import KoopmanModel

TORQUE, STEER = 0, 1  # input order [torque, steer]
#: The vehicle states the MPC predicts and constrains, first in every model's state.
VEHICLE_STATES = ("vx", "vy", "yaw_rate")
#: Model states the ECU measures, by the model's state name -> the sample's field. A
#: model may add the measured front wheel angle (the steering actuator's state, so that
#: the lift sees the tyres' slip and the actuator lag) after the vehicle states.
MEASURED_STATES = {"vx": "vx", "vy": "vy", "yaw_rate": "yaw_rate", "steer_measured": "steer_angle"}


def decayed_sums(A: np.ndarray, n_pred: int, decay: float) -> np.ndarray:
    """D_i = sum_{j<i} A^(i-1-j) decay^j for i = 0..Np, shape (Np + 1, n_z, n_z).

    The lifted state at step i gained from an additive input decay^j w at every step j < i
    is D_i w; decay = 1 gives S_i = sum_{j<i} A^j (a constant input).
    """
    n_z = A.shape[0]
    identity = np.eye(n_z)  # once, not per step: np.eye per step was a tenth of a speed quantum's set-up
    sums = np.zeros((n_pred + 1, n_z, n_z))
    for i in range(n_pred):
        sums[i + 1] = A @ sums[i] + decay ** i * identity  # D_{i+1} = A D_i + decay^i I
    return sums


def held_input_basis(free_from_lifted: np.ndarray, n_ctrl: int) -> np.ndarray:
    """G[i, :, c] = sum_j hold[j, c] F[i-1-j] for the held-input map, (Np + 1, n_x, Nc, n_z).

    free_from_lifted F (Np + 1, n_x, n_z). U_c (c < Nc - 1) acts at step c alone, so its
    column is a shifted copy of F; the last input is held from step Nc - 1 on, so its
    column sums F[i-1-j] over j = Nc - 1 .. i - 1, added in that order. That is the order
    (and the values) of the per-step einsum it replaces, at a quarter of its time: the
    same bits on every speed quantum of the committed artefacts (tests/test_lifted_mpc_maps.py).
    """
    n_steps, n_x, n_z = free_from_lifted.shape
    n_pred = n_steps - 1
    basis = np.zeros((n_steps, n_x, n_ctrl, n_z))
    for c in range(min(n_ctrl - 1, n_pred)):
        basis[c + 1:, :, c] = free_from_lifted[:n_pred - c]
    last = n_ctrl - 1
    for j in range(last, n_pred):
        basis[j + 1:, :, last] += free_from_lifted[:n_pred - j]
    return basis


@dataclass(frozen=True)
class PredictionMaps:
    """The horizon maps of one linear lifted model (A, B, offset), built once per model.

    free_from_lifted (Np + 1, n_x, n_z) = C_P A^i; free_from_drift (Np + 1, n_x, n_z) =
    C_P S_i; gain_basis (Np + 1, n_x, Nc, n_z) with G[i, :, c] = sum_j hold[j, c] C_P
    A^(i-1-j) (the response to a unit steer column b, so gain[i] = G[i] @ b); gain
    (Np + 1, n_x, Nc) for the model's own B; the model itself (its B and offset).
    """

    model: "KoopmanModel"
    free_from_lifted: np.ndarray
    free_from_drift: np.ndarray
    gain_basis: np.ndarray
    gain: np.ndarray

    @classmethod
    def build(cls, model: "KoopmanModel", hold: np.ndarray) -> "PredictionMaps":
        """Maps of ``model`` for the held-input map ``hold`` (Np, Nc)."""
        n_pred, n_z = hold.shape[0], model.n_z
        powers = np.empty((n_pred + 1, n_z, n_z))
        powers[0] = np.eye(n_z)
        for i in range(n_pred):
            powers[i + 1] = model.A @ powers[i]
        vehicle = model.C_P[:len(VEHICLE_STATES)]  # the states the QP sees
        free_from_lifted = vehicle @ powers
        if np.array_equal(hold, held_input_map(n_pred, hold.shape[1])):
            gain_basis = held_input_basis(free_from_lifted, hold.shape[1])
        else:
            gain_basis = np.zeros((n_pred + 1, len(VEHICLE_STATES), hold.shape[1], n_z))
            for i in range(1, n_pred + 1):
                gain_basis[i] = np.einsum("jc,jxz->xcz", hold[:i], free_from_lifted[i - 1::-1])
        return cls(model, free_from_lifted, vehicle @ decayed_sums(model.A, n_pred, 1.0), gain_basis,
                   gain_basis @ model.B[:, STEER])


class LiftedMpc(QpSteeringMpc):
    """Steering MPC on a ``KoopmanModel`` (A, B, offset, C_P, lift). DKMPC as is.

    The scheduled form's maps are those of ``model.at_speed(vx)`` at the measured speed,
    built on first use and cached per speed quantum (as LMPC caches its bicycle). A bilinear
    model (or a scheduled one with a bilinear term) holds its B(z_k) over the horizon.
    """

    def __init__(self, model: "KoopmanModel", tuning: QpMpcTuning, longitudinal: LongitudinalTuning) -> None:
        names = tuple(model.state_names)
        if names[:3] != VEHICLE_STATES or any(n not in MEASURED_STATES for n in names):
            raise ControllerError(f"the Koopman model's states {names} must start with {VEHICLE_STATES} and "
                                  f"be measured by the ECU (known: {', '.join(MEASURED_STATES)})")
        self.model = model
        self._measured_fields = tuple(MEASURED_STATES[n] for n in names)
        super().__init__(tuning, longitudinal)
        self._scheduled = model.form == "scheduled"
        self._maps_cache: dict[int, PredictionMaps] = {}
        self._fixed_maps = None if self._scheduled else PredictionMaps.build(model, self.hold)
        self.lifted_state: np.ndarray | None = None  # z_k of the last step

    def prediction_maps(self, speed: float) -> PredictionMaps:
        """The maps of the model at ``speed`` (the one model unless scheduled)."""
        if self._fixed_maps is not None:
            return self._fixed_maps
        local = self.model.at_speed(speed)
        maps = self._maps_cache.get(id(local))
        if maps is None or maps.model is not local:
            if len(self._maps_cache) > 2048:
                self._maps_cache.clear()
            maps = self._maps_cache[id(local)] = PredictionMaps.build(local, self.hold)
        return maps

    def disturbance_response(self, lifted_state: np.ndarray, maps: PredictionMaps) -> np.ndarray | float:
        """The disturbance estimate's share of the states at steps 0..Np, (Np + 1, 3); 0 for DKMPC."""
        return 0.0

    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """States [vx, vy, yaw_rate] at steps 0..Np: free (Np + 1, 3), gain (Np + 1, 3, Nc)."""
        lifted = self.model.lift(np.array([getattr(sample, field) for field in self._measured_fields]))
        self.lifted_state = lifted
        maps = self.prediction_maps(sample.vx)
        input_matrix, gain = maps.model.B, maps.gain
        if maps.model.form == "bilinear":  # B(z_k), held over the horizon (also a scheduled model's at_speed)
            input_matrix = maps.model.input_matrix(lifted)
            gain = maps.gain_basis @ input_matrix[:, STEER]
        drift = input_matrix[:, TORQUE] * drive_torque + maps.model.offset
        # What shift_start steps the lifted state with (no copies: references only).
        self._start_model = (maps, input_matrix, drift)
        free = (maps.free_from_lifted @ lifted + maps.free_from_drift @ drift
                + self.disturbance_response(lifted, maps))
        return free, gain

    def disturbance_input(self) -> np.ndarray | float:
        """The estimate w_hat (n_z,) added to every step of the last prediction; 0 for DKMPC."""
        return 0.0

    def shift_start(self, free: np.ndarray, window: DelayWindow) -> np.ndarray:
        """The lifted state z_k moved over ``window`` by the step's own model,
        z+ = A z + B_k [T, steer] + offset + w_hat (B_k, T as the prediction holds them),
        and the free response (Np + 1, 3) from there: free + C_P A^i (z_d - z_k)."""
        maps, input_matrix, drift = self._start_model
        transition, steer_column, disturbance = maps.model.A, input_matrix[:, STEER], self.disturbance_input()
        lifted = self.lifted_state
        moved = forward_state(lambda z, steer: transition @ z + steer_column * steer + drift + disturbance,
                              lifted, window)
        return free + maps.free_from_lifted @ (moved - lifted)

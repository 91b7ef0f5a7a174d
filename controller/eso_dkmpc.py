"""ESO-DKMPC (paper eq. 15): Koopman MPC with the ESO's disturbance estimate (eq. 13).

Each step: lift the measured state z_k; the estimate used over the horizon is
w_hat[k+1] = w_hat[k] - beta2 (z_k - z_hat_k), which already contains z_k
(``models.eso.innovated_disturbance``). Prediction step i adds ``decay**i * w_hat``
(``disturbance_decay`` of the tuning; 1 = held over the horizon as in eq. 15). The gains
place the two error poles of eq. 24 at ``eso_pole`` and ``eso_second_pole`` (a fast and a
slow one, see ``models.eso.design_gains``); the correction g2 bounds the innovation's vy and
yaw-rate entries (``eso_innovation_limit``, ``models.eso.InnovationSaturation``). After
the command u_k is known the observer advances with (z_k, u_k). Restarts and fallbacks: ``controller.observed_mpc`` (shared with
the LMPC-ESO ablation).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controller.base import Command, VehicleSample
from controller.lifted_mpc import VEHICLE_STATES, LiftedMpc, PredictionMaps, decayed_sums
from controller.observed_mpc import ObservedMpc
from controller.tuning import ControllerTuning, EsoDkmpcTuning, LongitudinalTuning
from models.eso import EsoParams, ExtendedStateObserver, design_gains
from models.eso_dk import observer_params

if TYPE_CHECKING:
    from models.koopman import KoopmanModel

#: Rows of vy and the yaw rate in the lifted state z = [x; Phi(x)] (the innovation bound's).
LATERAL_ROWS = (VEHICLE_STATES.index("vy"), VEHICLE_STATES.index("yaw_rate"))
#: The rows of the measured speed and yaw rate: their product is the lateral acceleration
#: that gates the innovation bound's widening.
SPEED_ROW, YAW_RATE_ROW = VEHICLE_STATES.index("vx"), VEHICLE_STATES.index("yaw_rate")


class EsoDkmpc(ObservedMpc, LiftedMpc):
    """Koopman MPC + extended state observer in the lifted space."""

    name = "eso-dkmpc"

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "EsoDkmpc":
        """Build with the trained Koopman artefact (``KoopmanModel.load()``)."""
        from models.koopman import KoopmanModel

        return cls(KoopmanModel.load(), tuning.eso_dkmpc, tuning.longitudinal)

    def __init__(self, model: "KoopmanModel", tuning: EsoDkmpcTuning, longitudinal: LongitudinalTuning) -> None:
        self._eso_tuning = tuning
        # Per linear model (one, or one per speed quantum of a scheduled model): observer
        # parameters and the disturbance's horizon map C_P D_i (Np + 1, n_x, n_z).
        self._observer_cache: dict[int, tuple["KoopmanModel", EsoParams, np.ndarray]] = {}
        super().__init__(model, tuning, longitudinal)
        params, _ = self._observer_for(self.prediction_maps(model.speed_knots[0] if self._scheduled else 0.0))
        self.observer = ExtendedStateObserver(params)

    def _observer_for(self, maps: PredictionMaps) -> tuple[EsoParams, np.ndarray]:
        """(ESO parameters, disturbance map) of the linear model behind ``maps``, cached.

        The matrix-structured gains beta1 = (p1 + p2 - 1) I - A place the error poles of
        eq. 24 whatever A is, so every speed's observer has the same error dynamics.
        """
        local = maps.model
        cached = self._observer_cache.get(id(local))
        if cached is None or cached[0] is not local:
            tuning = self._eso_tuning
            gains = design_gains(local.A, tuning.eso_pole, second_pole=tuning.eso_second_pole, structure="matrix")
            params = observer_params(local if self._scheduled else self.model, gains.beta1, gains.beta2,
                                     self.innovation_bound(LATERAL_ROWS))
            if tuning.disturbance_decay == 1.0:
                # A held estimate enters as a constant input does: C_P S_i, the very product
                # the maps already hold (same operands, same bits), so it is not built twice.
                horizon_map = maps.free_from_drift
            else:
                decayed = decayed_sums(local.A, tuning.prediction_horizon, tuning.disturbance_decay)
                horizon_map = local.C_P[:len(VEHICLE_STATES)] @ decayed
            if len(self._observer_cache) > 2048:
                self._observer_cache.clear()
            cached = self._observer_cache[id(local)] = (local, params, horizon_map)
        return cached[1], cached[2]

    def disturbance_response(self, lifted_state: np.ndarray, maps: PredictionMaps) -> np.ndarray:
        """States' share (Np + 1, 3) of w_hat, shaped over the horizon by the decay; the
        observer runs on the model of this step's speed (scheduled form)."""
        params, free_from_disturbance = self._observer_for(maps)
        self.observer.params = params
        self._disturbance_estimate = self.disturbance(lifted_state)
        return free_from_disturbance @ self._disturbance_estimate

    def disturbance_input(self) -> np.ndarray:
        """w_hat (n_z,) of the last prediction (held over the delay window, decay^0)."""
        return self._disturbance_estimate

    def _after_command(self, sample: VehicleSample, command: Command) -> None:
        lifted = self.lifted_state
        self.observe(lifted, np.array([command.drive_torque, command.steer_angle]),
                     float(lifted[SPEED_ROW] * lifted[YAW_RATE_ROW]))

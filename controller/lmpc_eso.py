"""LMPC-ESO (ablation, offset-free LMPC): LMPC's linear bicycle plus ESO-DKMPC's observer.

What the observer contributes without the learned lift: the same eq. 13 observer as
ESO-DKMPC, with gains from the same ``models.eso.design_gains(A, eso_pole,
second_pole=eso_second_pole, structure="matrix")`` and the same tuning fields, run in the
physical state space of LMPC's model.

Observer state: LMPC's lateral state x = [vy, yaw_rate], input the front wheel angle, model
(A, B) = the bicycle discretised at the measured vx (``Lmpc._prediction_maps``' speed
quantum, so the observer's model is exactly the one the MPC predicts with). We do not add a
vx row: LMPC holds vx at the measured value over the horizon (the P controller owns vx),
and an observer on a held vx would estimate the acceleration as a "disturbance" and turn
the held vx into a ramp, changing LMPC's prediction structure instead of correcting it.

Prediction: LMPC's free response plus the estimate's share, held over the horizon with the
tuning's decay as in ESO-DKMPC: step i adds D_i w_hat, D_i = sum_{j<i} A^(i-1-j) decay^j
(``controller.lifted_mpc.decayed_sums``). Restarts and fallbacks as ESO-DKMPC
(``controller.observed_mpc``).
"""
from __future__ import annotations

import numpy as np

from controller.base import Command, VehicleSample
from controller.lifted_mpc import decayed_sums
from controller.lmpc import MIN_MODEL_SPEED, SPEED_QUANTUM, DiscreteLateralModel, Lmpc
from controller.observed_mpc import ObservedMpc
from controller.tuning import ControllerTuning, EsoQpMpcTuning, LongitudinalTuning
from models.eso import EsoParams, ExtendedStateObserver, design_gains

#: Observer designs kept per speed quantum before the cache is emptied (a lane change at
#: varying speed visits a few hundred).
_OBSERVER_CACHE_SIZE = 4096


class LmpcEso(ObservedMpc, Lmpc):
    """LMPC on the 2-DoF bicycle with the eq. 13 observer on [vy, yaw_rate]."""

    name = "lmpc-eso"

    def __init__(self, bicycle: DiscreteLateralModel, tuning: EsoQpMpcTuning,
                 longitudinal: LongitudinalTuning) -> None:
        self._eso_tuning = tuning
        # Speed quantum -> (observer parameters, disturbance horizon map D_i (Np + 1, 2, 2)).
        self._observer_cache: dict[int, tuple[EsoParams, np.ndarray]] = {}
        super().__init__(bicycle, tuning, longitudinal)
        self.observer = ExtendedStateObserver(self._observer_for(MIN_MODEL_SPEED)[0])
        self.lateral_state: np.ndarray | None = None  # [vy, yaw_rate] of the last step

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "LmpcEso":
        """Build with the nominal bicycle model of ``models.bicycle`` (LMPC's)."""
        from models.bicycle import LinearBicycle

        return cls(LinearBicycle(), tuning.lmpc_eso, tuning.longitudinal)

    def _observer_for(self, vx: float) -> tuple[EsoParams, np.ndarray]:
        """(ESO parameters, disturbance horizon map (Np + 1, 2, 2)) of the bicycle at vx,
        on LMPC's speed grid, cached. The matrix-structured gains place the error poles of
        eq. 24 at the tuning's poles whatever the speed's A is."""
        key = round(max(vx, MIN_MODEL_SPEED) / SPEED_QUANTUM)
        cached = self._observer_cache.get(key)
        if cached is not None:
            return cached
        tuning = self._eso_tuning
        a, b = self.bicycle.discrete_matrices(key * SPEED_QUANTUM, self.ts)
        a = np.asarray(a, dtype=float)
        gains = design_gains(a, tuning.eso_pole, second_pole=tuning.eso_second_pole, structure="matrix")
        params = EsoParams(a, np.asarray(b, dtype=float).reshape(2, 1), np.zeros(2), gains.beta1, gains.beta2,
                           g2=self.innovation_bound((0, 1)))  # the state is [vy, yaw_rate]
        if len(self._observer_cache) >= _OBSERVER_CACHE_SIZE:
            self._observer_cache.clear()
        cached = self._observer_cache[key] = (
            params, decayed_sums(a, tuning.prediction_horizon, tuning.disturbance_decay))
        return cached

    def disturbance_response(self, sample: VehicleSample) -> np.ndarray:
        """The estimate's share of [vy, yaw_rate] at steps 0..Np, (Np + 1, 2); the observer
        runs on the bicycle at this step's speed."""
        params, horizon_map = self._observer_for(sample.vx)
        self.observer.params = params
        self.lateral_state = np.array([sample.vy, sample.yaw_rate])
        return horizon_map @ self.disturbance(self.lateral_state)

    def predict_states(self, sample: VehicleSample, drive_torque: float) -> tuple[np.ndarray, np.ndarray]:
        """LMPC's free (Np + 1, 3) plus the disturbance share on [vy, yaw_rate]; gain
        (Np + 1, 3, Nc) unchanged (the estimate does not depend on the steer sequence)."""
        free, gain = super().predict_states(sample, drive_torque)
        free[:, 1:] += self.disturbance_response(sample)  # free is a fresh array each step
        return free, gain

    def _after_command(self, sample: VehicleSample, command: Command) -> None:
        self.observe(self.lateral_state, np.array([command.steer_angle]), sample.vx * float(self.lateral_state[1]))

"""ESO-DKMPC (paper eq. 15): Koopman MPC with the ESO's disturbance estimate (eq. 13).

Each step: lift the measured state z_k; the estimate used over the horizon is
w_hat[k+1] = w_hat[k] - beta2 (z_k - z_hat_k), which already contains z_k
(``models.eso.innovated_disturbance``); after the command u_k is known the observer
advances with (z_k, u_k). The observer restarts at z_k (zero estimate, flagged
``observer_reset``) on the first step, after ``reset()`` and after any step that did
not see a valid sample (status NOT_RUN), because then the observer's last (z, u) no
longer describes the transition into the next sample. After a solver fallback the
observer advances with the fallback command, which is what the vehicle received.
"""
from __future__ import annotations

import numpy as np

from controller.base import Command, VehicleSample
from controller.lifted_mpc import LiftedMpc
from controller.tuning import ControllerTuning, EsoDkmpcTuning, LongitudinalTuning


class EsoDkmpc(LiftedMpc):
    """Koopman MPC + extended state observer in the lifted space."""

    name = "eso-dkmpc"

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "EsoDkmpc":
        """Build with the trained Koopman artefact (``KoopmanModel.load()``)."""
        from models.koopman import KoopmanModel

        return cls(KoopmanModel.load(), tuning.eso_dkmpc, tuning.longitudinal)

    def __init__(self, model, tuning: EsoDkmpcTuning, longitudinal: LongitudinalTuning) -> None:
        from models.eso import EsoParams, ExtendedStateObserver, design_gains

        gains = design_gains(model.A, tuning.eso_pole, structure="matrix")
        self.observer = ExtendedStateObserver(
            EsoParams(model.A, model.B, model.offset, gains.beta1, gains.beta2))
        self._observer_running = False
        super().__init__(model, tuning, longitudinal)

    def reset(self) -> None:
        """Forget plans, progress and the observer state."""
        self._observer_running = False
        super().reset()

    def disturbance(self, lifted_state: np.ndarray) -> np.ndarray:
        from models.eso import innovated_disturbance

        if not self._observer_running:
            self.observer.reset(lifted_state)
            self._observer_running = True
            self._observer_reset = True
            return self.observer.disturbance_estimate
        return innovated_disturbance(self.observer.state, lifted_state, self.observer.params)

    def _after_command(self, sample: VehicleSample, command: Command) -> None:
        accepted = self.observer.update(self.lifted_state, np.array([command.drive_torque, command.steer_angle]))
        if not accepted:
            self._observer_running = False

    def _fallback(self, status, torque, plan=None, sample=None):
        if sample is None:  # no valid measurement this step: restart on the next good one
            self._observer_running = False
        return super()._fallback(status, torque, plan, sample)

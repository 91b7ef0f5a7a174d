"""ESO-DKMPC (paper eq. 15): Koopman MPC with the ESO's disturbance estimate (eq. 13).

Each step: lift the measured state z_k; the estimate used over the horizon is
w_hat[k+1] = w_hat[k] - beta2 (z_k - z_hat_k), which already contains z_k
(``models.eso.innovated_disturbance``). Prediction step i adds ``decay**i * w_hat``
(``disturbance_decay`` of the tuning; 1 = held over the horizon as in eq. 15). The gains
place the two error poles of eq. 24 at ``eso_pole`` and ``eso_second_pole`` (a fast and a
slow one, see ``models.eso.design_gains``). After the command u_k is known the observer
advances with (z_k, u_k). The observer restarts at z_k (zero estimate, flagged
``observer_reset``) on the first step, after ``reset()`` and after any step that did
not see a valid sample (status NOT_RUN), because then the observer's last (z, u) no
longer describes the transition into the next sample. After a solver fallback the
observer advances with the fallback command, which is what the vehicle received.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controller.base import Command, SolverStatus, StepDebug, VehicleSample
from controller.lifted_mpc import LiftedMpc, decayed_sums
from controller.mpc_base import Plan
from controller.tuning import ControllerTuning, EsoDkmpcTuning, LongitudinalTuning
from models.eso import EsoParams, ExtendedStateObserver, design_gains, innovated_disturbance

if TYPE_CHECKING:
    from models.koopman import KoopmanModel


class EsoDkmpc(LiftedMpc):
    """Koopman MPC + extended state observer in the lifted space."""

    name = "eso-dkmpc"

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "EsoDkmpc":
        """Build with the trained Koopman artefact (``KoopmanModel.load()``)."""
        from models.koopman import KoopmanModel

        return cls(KoopmanModel.load(), tuning.eso_dkmpc, tuning.longitudinal)

    def __init__(self, model: "KoopmanModel", tuning: EsoDkmpcTuning, longitudinal: LongitudinalTuning) -> None:
        gains = design_gains(model.A, tuning.eso_pole, second_pole=tuning.eso_second_pole, structure="matrix")
        self.observer = ExtendedStateObserver(
            EsoParams(model.A, model.B, model.offset, gains.beta1, gains.beta2))
        self._observer_running = False
        super().__init__(model, tuning, longitudinal)
        decayed = decayed_sums(model.A, tuning.prediction_horizon, tuning.disturbance_decay)
        self._free_from_disturbance = model.C_P @ decayed  # (Np + 1, n_x, n_z)

    def reset(self) -> None:
        """Forget plans, progress and the observer state."""
        self._observer_running = False
        super().reset()

    def disturbance(self, lifted_state: np.ndarray) -> np.ndarray:
        """w_hat (n_z,) including the measurement z_k; restarts the observer when needed."""
        if not self._observer_running:
            self.observer.reset(lifted_state)
            self._observer_running = True
            self._observer_reset = True
            return self.observer.disturbance_estimate
        return innovated_disturbance(self.observer.state, lifted_state, self.observer.params)

    def disturbance_response(self, lifted_state: np.ndarray) -> np.ndarray:
        """States' share (Np + 1, 3) of w_hat, shaped over the horizon by the decay."""
        return self._free_from_disturbance @ self.disturbance(lifted_state)

    def _after_command(self, sample: VehicleSample, command: Command) -> None:
        accepted = self.observer.update(self.lifted_state, np.array([command.drive_torque, command.steer_angle]))
        if not accepted:
            self._observer_running = False

    def _fallback(self, status: SolverStatus, torque: float | None, plan: Plan | None = None,
                  sample: VehicleSample | None = None) -> tuple[Command, StepDebug]:
        if sample is None:  # no valid measurement this step: restart on the next good one
            self._observer_running = False
        return super()._fallback(status, torque, plan, sample)

"""DKMPC: the deep Koopman MPC without the observer (w_hat = 0), paper Section IV-B 4)."""
from __future__ import annotations

from controller.lifted_mpc import LiftedMpc
from controller.tuning import ControllerTuning


class Dkmpc(LiftedMpc):
    """Steering MPC on the learned Koopman model alone."""

    name = "dkmpc"

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "Dkmpc":
        """Build with the trained Koopman artefact (``KoopmanModel.load()``)."""
        from models.koopman import KoopmanModel

        return cls(KoopmanModel.load(), tuning.dkmpc, tuning.longitudinal)

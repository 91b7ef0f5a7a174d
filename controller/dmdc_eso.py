"""DMDc-ESO (ablation): ESO-DKMPC with no lift, so a reader sees what the lift contributes.

The same observer (eq. 13 with ``design_gains``) and MPC (eq. 15) code as ESO-DKMPC
(``controller.eso_dkmpc.EsoDkmpc``, the same tuning fields), on a linear model
x+ = A x + B u + c fitted by least squares (DMDc) with z = x: n_z = 3, the observer runs in
the physical state space [vx, vy, yaw_rate], inputs [torque, steer]. The model is the
committed artefact ``models/artifacts/dmdc.{npz,json}`` (``make dmdc``), fitted on the
training runs of the default deep Koopman artefact's data and split.
"""
from __future__ import annotations

from controller.eso_dkmpc import EsoDkmpc
from controller.tuning import ControllerTuning


class DmdcEso(EsoDkmpc):
    """ESO-DKMPC on the DMDc model (z = x)."""

    name = "dmdc-eso"

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "DmdcEso":
        """Build with the DMDc artefact (``models.dmdc_model.load_dmdc_model()``)."""
        from models.dmdc_model import load_dmdc_model

        return cls(load_dmdc_model(), tuning.dmdc_eso, tuning.longitudinal)

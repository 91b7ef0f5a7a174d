"""The controllers of a campaign cell that names a ``model`` (a Koopman artefact), built the
same way on both runners: ``hil`` (``studies.campaign.cell``, as the ECU's controller
factory) and ``closed_loop`` (``studies.campaign.closed_loop_cell``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any


def model_factory(artefact: Path, tuning: Any = None) -> Any:
    """A ``controller_factory`` building the Koopman controllers on ``artefact``, from the
    ``ControllerTuning`` ``tuning`` (default: ``controller/tuning.toml``)."""

    def build(name: str) -> Any:
        from controller.registry import CONTROLLERS, create_controller
        from controller.tuning import load_tuning
        from models.koopman import KoopmanModel

        if name not in ("eso-dkmpc", "dkmpc"):
            if tuning is not None:
                from studies.campaign.tuning_override import build_controller

                return build_controller(name, tuning)
            return create_controller(name)
        import importlib

        module, class_name = CONTROLLERS[name]
        controller_class = getattr(importlib.import_module(module), class_name)
        tables = load_tuning() if tuning is None else tuning
        table = tables.eso_dkmpc if name == "eso-dkmpc" else tables.dkmpc
        return controller_class(KoopmanModel.load(artefact), table, tables.longitudinal)

    return build

"""The controllers of a campaign cell that names a ``model`` (a Koopman artefact), built the
same way on both runners: ``hil`` (``studies.campaign.cell``, as the ECU's controller
factory) and ``closed_loop`` (``studies.campaign.closed_loop_cell``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any


def model_factory(artefact: Path) -> Any:
    """A ``controller_factory`` building the Koopman controllers on ``artefact``."""

    def build(name: str) -> Any:
        from controller.registry import CONTROLLERS, create_controller
        from controller.tuning import load_tuning
        from models.koopman import KoopmanModel

        if name not in ("eso-dkmpc", "dkmpc"):
            return create_controller(name)
        import importlib

        module, class_name = CONTROLLERS[name]
        controller_class = getattr(importlib.import_module(module), class_name)
        tuning = load_tuning()
        table = tuning.eso_dkmpc if name == "eso-dkmpc" else tuning.dkmpc
        return controller_class(KoopmanModel.load(artefact), table, tuning.longitudinal)

    return build

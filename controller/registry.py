"""Controllers by name: a lazy name -> (module, class) table, as python-can's BACKENDS.

Only the chosen controller's module (and its model: torch-free numpy, or CasADi for NMPC)
is imported. Building loads the tuning and the model files: build time, never step time.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from controller.base import Controller
from controller.errors import UnknownControllerError
from controller.tuning import load_tuning

#: The paper's four controllers: the default set of ``make run``, the timing studies and
#: the fault campaign.
CONTROLLER_NAMES = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
#: Ablations (issue 14 item 6), extra rows of the study (``make tables``): the observer on
#: LMPC's bicycle (offset-free LMPC) and ESO-DKMPC on a DMDc model (no lift).
ABLATION_NAMES = ("lmpc-eso", "dmdc-eso")
#: Every name ``create_controller`` builds (the ECU's ``--controller`` choices).
ALL_CONTROLLER_NAMES = CONTROLLER_NAMES + ABLATION_NAMES

#: name -> (module, class); each class has ``from_tuning(ControllerTuning)``.
CONTROLLERS: dict[str, tuple[str, str]] = {
    "eso-dkmpc": ("controller.eso_dkmpc", "EsoDkmpc"),
    "dkmpc": ("controller.dkmpc", "Dkmpc"),
    "lmpc": ("controller.lmpc", "Lmpc"),
    "nmpc": ("controller.nmpc", "Nmpc"),
    "lmpc-eso": ("controller.lmpc_eso", "LmpcEso"),
    "dmdc-eso": ("controller.dmdc_eso", "DmdcEso"),
}


def create_controller(name: str, tuning_path: str | Path | None = None) -> Controller:
    """Build controller ``name`` (one of ``ALL_CONTROLLER_NAMES``) with the tuning file
    (default ``controller/tuning.toml``). Raises ``UnknownControllerError`` for other
    names, ``TuningError`` for a bad tuning file and the model package's errors for a
    missing or bad model artefact."""
    if name not in CONTROLLERS:
        raise UnknownControllerError(f"unknown controller {name!r}; choose one of {', '.join(ALL_CONTROLLER_NAMES)}")
    tuning = load_tuning(tuning_path)
    module_name, class_name = CONTROLLERS[name]
    controller_class = getattr(importlib.import_module(module_name), class_name)
    return controller_class.from_tuning(tuning)

"""Controllers built from the committed tuning file with fields of one table replaced: how
tests turn on what the shipped tuning leaves off (the heading target's slip, the yaw-rate
bias estimate) without writing a tuning file."""
from __future__ import annotations

import dataclasses
import importlib

from controller.base import Controller
from controller.registry import CONTROLLERS
from controller.tuning import ControllerTuning, load_tuning


def tuning_with(name: str, **fields: object) -> ControllerTuning:
    """``controller/tuning.toml`` with controller ``name``'s table (registry name, e.g.
    ``"eso-dkmpc"``) having ``fields`` replaced; every other table as committed."""
    tuning = load_tuning()
    table = dataclasses.replace(tuning.for_controller(name), **fields)
    return dataclasses.replace(tuning, **{name.replace("-", "_"): table})


def controller_with(name: str, **fields: object) -> Controller:
    """Controller ``name`` of the registry built by its class's ``from_tuning`` from
    `tuning_with` ``(name, **fields)`` (its default model artefact)."""
    module, class_name = CONTROLLERS[name]
    return getattr(importlib.import_module(module), class_name).from_tuning(tuning_with(name, **fields))

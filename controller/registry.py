"""Controllers by name: a lazy name -> (module, class) table, as python-can's BACKENDS.

Only the chosen controller's module (and its model: torch-free numpy, or CasADi for NMPC)
is imported. Building loads the tuning and the model files: build time, never step time.
"""
from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path

from controller.base import Controller
from controller.errors import ControllerError, UnknownControllerError
from controller.tuning import load_tuning

#: The paper's four controllers: the default set of ``make run``, the timing studies and
#: the fault campaign.
CONTROLLER_NAMES = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
#: Ablations (issue 14 item 6), extra rows of the study (``make tables``): the observer on
#: LMPC's bicycle (offset-free LMPC) and ESO-DKMPC on a DMDc model (no lift).
ABLATION_NAMES = ("lmpc-eso", "dmdc-eso")
#: Geometric baselines (issue 35 item 5): no model and no horizon, so that a reader sees
#: what the MPCs buy. Not among the paper's four (the studies that key on those stay as
#: they are); the C ECU has none of them.
GEOMETRIC_NAMES = ("stanley",)
#: Every name ``create_controller`` builds (the ECU's ``--controller`` choices).
ALL_CONTROLLER_NAMES = CONTROLLER_NAMES + ABLATION_NAMES + GEOMETRIC_NAMES
#: The model-predictive controllers (every name but the geometric baselines).
MPC_NAMES = CONTROLLER_NAMES + ABLATION_NAMES

#: name -> (module, class); each class has ``from_tuning(ControllerTuning)``.
CONTROLLERS: dict[str, tuple[str, str]] = {
    "eso-dkmpc": ("controller.eso_dkmpc", "EsoDkmpc"),
    "dkmpc": ("controller.dkmpc", "Dkmpc"),
    "lmpc": ("controller.lmpc", "Lmpc"),
    "nmpc": ("controller.nmpc", "Nmpc"),
    "lmpc-eso": ("controller.lmpc_eso", "LmpcEso"),
    "dmdc-eso": ("controller.dmdc_eso", "DmdcEso"),
    "stanley": ("controller.stanley", "Stanley"),
}


def create_controller(name: str, tuning_path: str | Path | None = None,
                      model_path: str | Path | None = None) -> Controller:
    """Build controller ``name`` (one of ``ALL_CONTROLLER_NAMES``) with the tuning file
    (default ``controller/tuning.toml``) and, with ``model_path``, another model file
    (``MODEL_FILE_KINDS``) instead of the default one. Raises ``UnknownControllerError``
    for other names, ``TuningError`` for a bad tuning file and the model package's errors
    for a missing or bad model artefact."""
    if name not in CONTROLLERS:
        raise UnknownControllerError(f"unknown controller {name!r}; choose one of {', '.join(ALL_CONTROLLER_NAMES)}")
    tuning = load_tuning(tuning_path)
    module_name, class_name = CONTROLLERS[name]
    controller_class = getattr(importlib.import_module(module_name), class_name)
    if model_path is None:
        return controller_class.from_tuning(tuning)
    return controller_class(load_controller_model(name, model_path),
                            tuning.for_controller(name), tuning.longitudinal)


class ModelFileError(ControllerError):
    """A ``--model`` file does not fit the controller (kind, states or inputs; names the file)."""


#: ``--model`` (another model file): controller -> the kind of file its constructor takes.
MODEL_FILE_KINDS: dict[str, str] = {"eso-dkmpc": "koopman", "dkmpc": "koopman",
                                    "lmpc": "bicycle", "lmpc-eso": "bicycle"}
#: The states and inputs an ECU model must have (the frames carry nothing else).
ECU_MODEL_INPUTS = ("torque", "steer")
#: The sample time (s) an ECU model must have: the contract's control period (25 ms).
ECU_MODEL_TS = 0.025
#: How far (s) a model's ts may be from ECU_MODEL_TS: rounding only (the C core's too).
ECU_MODEL_TS_TOLERANCE = 1e-9


def load_controller_model(name: str, model_path: str | Path) -> object:
    """The model file for controller ``name``: a Koopman artefact (``.npz`` + ``.json``)
    or a fitted bicycle file (JSON of ``models.bicycle_fit``).

    Raises:
        ModelFileError: the controller takes no model file, or the file is of the other
            kind, or a Koopman model whose inputs or states the ECU cannot supply (a model
            for study, e.g. one trained on throttle and brake).
        models.errors.ModelError: the file does not load.
    """
    kind = MODEL_FILE_KINDS.get(name)
    if kind is None:
        raise ModelFileError(f"--model: controller {name!r} takes no model file (those that do: "
                             f"{', '.join(MODEL_FILE_KINDS)})")
    if kind == "bicycle":
        from models.bicycle_fit import load_bicycle
        return load_bicycle(model_path)
    from models.koopman import KoopmanModel
    model = KoopmanModel.load(model_path)
    check_ecu_model_names(model.state_names, model.input_names, str(model_path))
    check_ecu_model_ts(model.ts, str(Path(model_path).with_suffix(".json")))
    return model


def check_ecu_model_ts(ts: float, where: str) -> None:
    """Refuse a Koopman model whose sample time is not the contract's control period: the
    MPC steps the model once a control period, and the C core's pose prediction uses the
    model's ts, so a model of another ts would steer differently in the two ECUs.

    Raises:
        ModelFileError: ``WHERE: the model's sample time ts ...``, the text the C core's data
            reader (firmware/src/ecu_data.c) gives for such a data file.
    """
    if not abs(ts - ECU_MODEL_TS) <= ECU_MODEL_TS_TOLERANCE:
        raise ModelFileError(f"{where}: the model's sample time ts {ts:g} s differs from the control period "
                             f"{ECU_MODEL_TS:g} s (train it with --ts {ECU_MODEL_TS:g})")


def check_ecu_model_names(states: Sequence[str], inputs: Sequence[str], where: str) -> None:
    """Refuse a Koopman model whose states or inputs the ECU cannot supply from the bus.

    Raises:
        ModelFileError: names the file, the model's states and inputs, and says that such
            a model is for study only.
    """
    from controller.lifted_mpc import MEASURED_STATES
    states, inputs = tuple(states), tuple(inputs)
    if inputs != ECU_MODEL_INPUTS or states[:3] != ("vx", "vy", "yaw_rate") \
            or not set(states) <= set(MEASURED_STATES):
        raise ModelFileError(
            f"--model {where}: a model of states {list(states)} and inputs {list(inputs)} is for "
            f"study only: the ECU's inputs are {list(ECU_MODEL_INPUTS)} and its states vx, vy, "
            f"yaw_rate (optionally {', '.join(sorted(set(MEASURED_STATES) - {'vx', 'vy', 'yaw_rate'}))}), "
            "as the bus carries them")

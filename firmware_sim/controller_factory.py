"""The ECU's controller factory for ``--model PATH`` (docs/identification.md): the registry's
controller built on another model file, a Koopman artefact for eso-dkmpc / dkmpc or a fitted
bicycle for lmpc / lmpc-eso. Used by the ECU's command line, ``hil run`` (in-process ECU)
and the C ECU's data-file check in ``hil.session``.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from firmware_sim.errors import ConfigError
from models.input_files import MODEL_FILE_MAX_BYTES, InputFileError, read_bounded


def model_controller_factory(controller: str, model: Path | None) -> Callable[[str], object] | None:
    """The ECU's controller factory for ``--model`` (None without it: the registry's default).

    A file the controller could never use is refused here, before the bus is opened: a
    controller without model files, a missing file, the other kind of file, a model whose
    states or inputs the bus does not carry (for study only). A file that passes these
    checks but does not load (damaged weights) latches FAULT in the ECU (contract).

    Raises:
        ConfigError: names the file and what is wrong with it.
    """
    if model is None:
        return None
    from controller.errors import ControllerError
    from controller.registry import MODEL_FILE_KINDS, check_ecu_model_names, create_controller
    kind = MODEL_FILE_KINDS.get(controller)
    if kind is None:
        raise ConfigError(f"--model {model}: controller {controller!r} takes no model file (those "
                          f"that do: {', '.join(MODEL_FILE_KINDS)})")
    other = _other_kind(model, kind)
    if other is not None:
        raise ConfigError(f"--model {model}: {other}; {controller} takes {_KIND_TEXT[kind]}")
    meta_file = model.with_suffix(".json") if kind == "koopman" else model
    for file in model_files(controller, model):
        if not file.is_file():
            raise ConfigError(f"--model {model}: {file} not found (a {kind} model file for "
                              f"{controller})")
    try:
        meta = json.loads(read_bounded(meta_file, MODEL_FILE_MAX_BYTES))
    except InputFileError as error:
        raise ConfigError(f"--model {model}: {error}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ConfigError(f"--model {model}: {meta_file} is not readable JSON: {error}") from error
    if not isinstance(meta, dict):
        raise ConfigError(f"--model {model}: {meta_file} is not a JSON object")
    if kind == "bicycle" and meta.get("kind") != "linear_bicycle":
        raise ConfigError(f"--model {model}: not a fitted bicycle file (kind {meta.get('kind')!r}); "
                          f"{controller} takes {_KIND_TEXT[kind]}")
    if kind == "koopman":
        try:
            check_ecu_model_names(meta.get("state_names", ()), meta.get("input_names", ()), str(model))
        except ControllerError as error:
            raise ConfigError(str(error)) from error
    return lambda name: create_controller(name, model_path=model)


#: What each kind of ``--model`` file is, for the messages.
_KIND_TEXT = {
    "koopman": "a Koopman artefact (PATH.npz + PATH.json, given as PATH: e.g. DIR/koopman of "
               "python -m models.koopman_train)",
    "bicycle": "a fitted bicycle file (JSON: e.g. DIR/bicycle.json of python -m "
               "models.koopman_train --logs)",
}


def _other_kind(model: Path, kind: str) -> str | None:
    """What ``model`` is when it is recognisably the other kind of model file (the message's
    start), else None: the checks that follow then name what is missing or wrong."""
    if kind == "koopman":
        json_file = model.with_suffix(".json")
        if _json_kind(json_file) != "linear_bicycle":
            return None
        return ("a fitted bicycle file" if json_file == model
                else f"{json_file} is a fitted bicycle file") + ", not a Koopman artefact"
    if model.with_suffix(".npz").is_file() and _json_kind(model) != "linear_bicycle":
        return "a Koopman artefact, not a fitted bicycle file"
    return None


def _json_kind(file: Path) -> object:
    """The ``kind`` field of a small JSON object file, or None (missing, unreadable, other)."""
    try:
        meta = json.loads(read_bounded(file, MODEL_FILE_MAX_BYTES))
    except (InputFileError, OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return meta.get("kind") if isinstance(meta, dict) else None


def model_files(controller: str, model: Path) -> list[Path]:
    """The files ``--model`` names for ``controller``: a Koopman artefact's weights and
    metadata (``.npz``, ``.json``), a fitted bicycle's JSON; none for a controller that takes
    no model file. What a log's sidecar records, with a hash of each."""
    from controller.registry import MODEL_FILE_KINDS

    kind = MODEL_FILE_KINDS.get(controller)
    if kind == "koopman":
        return [model.with_suffix(".npz"), model.with_suffix(".json")]
    return [] if kind is None else [model]

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
    meta_file = model.with_suffix(".json") if kind == "koopman" else model
    needed = [model.with_suffix(".npz"), meta_file] if kind == "koopman" else [model]
    for file in needed:
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
                          f"{controller} takes the bicycle JSON of python -m models.koopman_train --logs")
    if kind == "koopman":
        if meta.get("kind") == "linear_bicycle":
            raise ConfigError(f"--model {model}: a fitted bicycle file; {controller} takes a "
                              "Koopman artefact")
        try:
            check_ecu_model_names(meta.get("state_names", ()), meta.get("input_names", ()), str(model))
        except ControllerError as error:
            raise ConfigError(str(error)) from error
    return lambda name: create_controller(name, model_path=model)

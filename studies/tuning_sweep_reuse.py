"""Reuse of a stored tuning sweep (``--reuse``, ``--merge`` of ``studies.tuning_sweep``): its
evaluations taken instead of running them again, its other controllers carried into the
reports as stored, and the model files whose change makes their controllers run again.
"""
from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

from controller.registry import MODEL_FILE_KINDS
from hil.errors import StudyError
from studies.tuning_sweep_executor import Evaluation
from studies.tuning_sweep_grids import Setting
from studies.tuning_sweep_procedure import ControllerSweep
from studies.tuning_sweep_report import sweep_from_document

#: The controllers that run on the default Koopman artefact.
KOOPMAN_CONTROLLERS = tuple(name for name, kind in MODEL_FILE_KINDS.items() if kind == "koopman")
#: The sweep's record of a model file (its context key) -> the controllers that run on it:
#: ``--reuse`` runs them again when the file changed.
ARTEFACT_USERS = {"Koopman artefact used": KOOPMAN_CONTROLLERS, "DMDc artefact used": ("dmdc-eso",)}


def reusable_evaluations(path: Path, scenario_names: Sequence[str],
                         artefacts: Mapping[str, str]) -> dict[tuple[str, Setting], Evaluation]:
    """The evaluations of the sweep document at ``path`` by (controller, setting), for
    ``--reuse``. Raises StudyError unless it ran the same scenarios.

    ``artefacts``: this sweep's model files by context key (``ARTEFACT_USERS``' keys ->
    ``artefact_description``). Where the stored sweep used another file (or did not record
    it), the evaluations of the controllers that run on it are left out, so they run again;
    the other controllers do not depend on that file."""
    try:
        document = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise StudyError(f"--reuse {path}: cannot read it: {e}") from e
    record = sweep_from_document(document)
    if list(record.names) != list(scenario_names):
        raise StudyError(f"--reuse {path}: it ran scenarios {record.names}, this sweep runs {list(scenario_names)}")
    rerun: set[str] = set()
    for key, description in artefacts.items():
        if record.context.get(key) != description:
            rerun.update(ARTEFACT_USERS[key])
            print(f"--reuse {path}: {key} {record.context.get(key)}, this sweep {description}: "
                  f"{', '.join(ARTEFACT_USERS[key])} run again")
    found = {}
    for sweep in record.sweeps:
        if sweep.controller in rerun:
            continue
        for evaluation in (*sweep.evaluations, *(() if sweep.before is None else (sweep.before,))):
            found[(sweep.controller, evaluation.setting)] = evaluation
    return found


def carried_sweeps(path: Path, scenario_names: Sequence[str], run_now: Sequence[str],
                   artefacts: Mapping[str, str]) -> list[ControllerSweep]:
    """The controllers of the sweep document at ``path`` that ``run_now`` does not name, as
    stored (``--merge``): they go into the reports unchanged.

    Raises:
        StudyError: the document ran other scenarios, or a carried controller runs on a model
            file (``ARTEFACT_USERS``) that changed since (or was not recorded): its stored
            runs would not be this sweep's.
    """
    try:
        record = sweep_from_document(json.loads(path.read_text()))
    except (OSError, json.JSONDecodeError) as e:
        raise StudyError(f"--merge {path}: cannot read it: {e}") from e
    if list(record.names) != list(scenario_names):
        raise StudyError(f"--merge {path}: it ran scenarios {record.names}, this sweep runs {list(scenario_names)}")
    carried = [sweep for sweep in record.sweeps if sweep.controller not in run_now]
    for key, description in artefacts.items():
        stale = [s.controller for s in carried if s.controller in ARTEFACT_USERS[key]]
        if stale and record.context.get(key) != description:
            raise StudyError(f"--merge {path}: {key} {record.context.get(key)}, this sweep {description}: "
                             f"the stored runs of {', '.join(stale)} are not this sweep's; name them in "
                             "--controllers to run them again")
    return carried


def merged_sweeps(stored: Sequence[ControllerSweep], fresh: Sequence[ControllerSweep]) -> list[ControllerSweep]:
    """``stored`` (the carried controllers) with ``fresh`` in place of a stored controller of
    the same name, in the stored order; fresh controllers new to it follow in their order."""
    by_name = {sweep.controller: sweep for sweep in fresh}
    merged = [by_name.pop(sweep.controller, sweep) for sweep in stored]
    return merged + [sweep for sweep in fresh if sweep.controller in by_name]


def artefact_description(path: Path) -> str:
    """``<file> sha256 <first 12 hex>`` of a model file the sweep used (the default Koopman
    artefact, the DMDc model)."""
    if not path.is_file():
        return f"{path.name} missing"
    return f"{path.name} sha256 {hashlib.sha256(path.read_bytes()).hexdigest()[:12]}"

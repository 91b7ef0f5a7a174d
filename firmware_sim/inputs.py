"""The files a command of the ECU reads, so that no output of the same command is ever one
of them (issue 38, items 2 and 3): the Python ECU's ``--timing-out`` and ``hil run``'s
``--log`` / ``--out`` are checked against this one list. The C ECU's executable makes the
same check on its own options (``firmware/src/ecu_main.c``, ``check_output_file``).
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from firmware_sim.excitation import SHIPPED_PROGRAMS


def model_files(model: Path | None) -> list[Path]:
    """The files of ``--model PATH``: PATH itself (a fitted bicycle's JSON, a data file)
    and a Koopman artefact's PATH.npz and PATH.json."""
    if model is None:
        return []
    model = Path(model)
    return [model, model.with_suffix(".npz"), model.with_suffix(".json")]


def program_file(excite: str | None) -> list[Path]:
    """The file of ``--excite PROGRAM`` (none for a shipped program's name)."""
    if excite is None or excite in SHIPPED_PROGRAMS:
        return []
    return [Path(excite)]


def command_inputs(paths: Iterable[Path] = (), *, dbc: Path | None = None, model: Path | None = None,
                   excite: str | None = None) -> list[Path]:
    """Every input file of an ECU command line: path files, DBC, model files, program file."""
    return [*(Path(path) for path in paths), *([Path(dbc)] if dbc is not None else []),
            *model_files(model), *program_file(excite)]

"""Checks of output paths before a command runs (issue 17): never one of the run's inputs,
never an existing file or another run's outputs unless the command was told to replace
them, and never a folder that does not exist (no folder is created silently).

Each check raises ``error`` (``models.errors.OutputPathError`` unless the caller gives its
own, as ``hil.output_paths`` does) naming the option, the path and the problem, so a CLI
prints one ``error:`` line and exits non-zero before anything has run or been written. The
checks live here, in the lowest layer that writes files, so the training CLI
(``models.koopman_train``), the ECU's ``--timing-out`` (``firmware_sim.cli``, with its
``ConfigError``) and the HIL's commands share one implementation; the C ECU's executable
words its own check alike (``firmware/src/ecu_main.c``), so both ECUs print the same line.
"""
from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from models.errors import OutputPathError


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.resolve() == b.resolve():
            return True
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_not_input(path: Path, option: str, inputs: Iterable[Path],
                    error: type[Exception] = OutputPathError) -> None:
    """Refuse ``path`` when it is (or links to) one of ``inputs``."""
    for source in inputs:
        if _same_file(path, Path(source)):
            raise error(f"{option} {path}: is one of the inputs of this run ({source})")


def check_output_file(path: Path, option: str, *, replace: bool = False,
                      inputs: Iterable[Path] = (), replace_option: str = "--replace",
                      error: type[Exception] = OutputPathError) -> None:
    """An output file: its folder exists and is writable; the file is not an input, not a
    folder, and does not exist unless ``replace``."""
    path = Path(path)
    check_not_input(path, option, inputs, error)
    parent = path.resolve().parent
    if not parent.is_dir():
        raise error(f"{option} {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise error(f"{option} {path}: is a folder")
    if path.exists():
        if not replace:
            raise error(f"{option} {path}: file exists (give {replace_option} to "
                                  "overwrite it)")
        if not os.access(path, os.W_OK):
            raise error(f"{option} {path}: file is not writable")
    elif not os.access(parent, os.W_OK | os.X_OK):
        raise error(f"{option} {path}: folder {path.parent} is not writable")


def check_output_folder(path: Path, option: str, owned_names: Iterable[str], *,
                        replace: bool = False, inputs: Iterable[Path] = (),
                        replace_option: str = "--replace",
                        error: type[Exception] = OutputPathError) -> None:
    """An output folder: its parent exists; it is not a file; if it exists it is writable
    and holds none of ``owned_names`` (another run's outputs) unless ``replace``; no input
    lies where an output will be written."""
    path = Path(path)
    names = tuple(owned_names)
    check_not_input(path, option, inputs, error)
    for name in names:
        check_not_input(path / name, option, inputs, error)
    if path.exists() and not path.is_dir():
        raise error(f"{option} {path}: is a file, expected a folder")
    if not path.exists():
        if not path.resolve().parent.is_dir():
            raise error(f"{option} {path}: folder {path.parent} does not exist")
        if not os.access(path.resolve().parent, os.W_OK | os.X_OK):
            raise error(f"{option} {path}: folder {path.parent} is not writable")
        return
    if not os.access(path, os.W_OK | os.X_OK):
        raise error(f"{option} {path}: folder is not writable")
    present = [name for name in names if (path / name).exists()]
    if present and not replace:
        raise error(f"{option} {path}: holds another run's outputs "
                              f"({', '.join(present)}); give {replace_option} to replace them")

"""The ECU's ``--path ID=FILE.csv`` arguments (docs/ecu.md), also taken by ``hil replay``
and ``hil decode``: which reference path file serves which PATH_ID.

Only the argument is checked here (an 8-bit ID, a readable file); the file's content is
checked when the ECU loads it, where a bad one latches FAULT (contract).
"""
from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from pathlib import Path

from firmware_sim.errors import PathArgumentError


def parse_path_argument(text: str) -> tuple[int, Path]:
    """``"ID=FILE.csv"`` -> (PATH_ID, file); the file must exist and be readable.

    Nothing is read from the file here: a pipe (``--path 1=<(cat dlc.csv)``) can be read
    only once, by the loader (issue 17, defect 1).

    Raises:
        PathArgumentError: no ``=``, an ID that is not an integer in 0..255, an empty file
            name or a file that cannot be opened for reading.
    """
    path_id_text, separator, file_text = text.partition("=")
    if not separator or not file_text:
        raise PathArgumentError(f"--path {text!r}: expected ID=FILE.csv")
    try:
        path_id = int(path_id_text, 10)
    except ValueError:
        raise PathArgumentError(f"--path {text!r}: ID {path_id_text!r} is not an integer") from None
    if not 0 <= path_id <= 255:
        raise PathArgumentError(f"--path {text!r}: ID {path_id} outside 0..255 (PATH_ID is 8 bit)")
    file = Path(file_text)
    try:
        mode = file.stat().st_mode
    except OSError as error:
        raise PathArgumentError(f"--path {text!r}: cannot read {file}: "
                                f"{error.strerror or error}") from error
    if stat.S_ISDIR(mode):
        raise PathArgumentError(f"--path {text!r}: cannot read {file}: it is a folder")
    if not os.access(file, os.R_OK):
        raise PathArgumentError(f"--path {text!r}: cannot read {file}: permission denied")
    return path_id, file


def parse_paths(items: Sequence[str]) -> dict[int, Path]:
    """All ``--path`` arguments; a PATH_ID given twice is an error."""
    paths: dict[int, Path] = {}
    for item in items:
        path_id, file = parse_path_argument(item)
        if path_id in paths:
            raise PathArgumentError(f"--path {item!r}: PATH_ID {path_id} given twice "
                                    f"(already {paths[path_id]})")
        paths[path_id] = file
    return paths

"""Size bounds of the input files, checked before or while reading, never after (issue 38):
memory stays bounded on any input (a pipe, ``/dev/zero``, a file of one huge line), and a
file over its bound is one message naming the file and the bound.

The text files both ECUs read (path CSVs, excitation programs) go through `bounded_lines`,
whose rules the C ECU's ``firmware/src/ecu_lines.c`` follows byte for byte, so both give
the same verdict on the same file: a line is at most `MAX_LINE_BYTES` bytes with its end
and holds no NUL byte; a file is at most its own limit in all. Other inputs are read whole
with `read_bounded` (at most ``limit + 1`` bytes are ever read). Their numbers are read
by `csv_number`, the C ECU's rule.
"""
from __future__ import annotations

import stat
from collections.abc import Iterator
from pathlib import Path

from can_defs.dbc import DBC_FILE_MAX_BYTES  # noqa: F401 (one bound, owned by the DBC loader)

#: Bytes of one line of a text input file, with its end (ecu_lines.h ``ECU_LINE_MAX``).
MAX_LINE_BYTES = 4096
#: Bytes of a path file (100,000 points of up to 160 bytes; ``ECU_PATH_FILE_MAX``).
PATH_FILE_MAX_BYTES = 16 * 1024 * 1024
#: Bytes of an excitation program file (``ECU_EXCITE_FILE_MAX``).
EXCITE_FILE_MAX_BYTES = 4 * 1024 * 1024
#: Bytes of a model file: a Koopman artefact's .npz or .json, a fitted bicycle's JSON.
MODEL_FILE_MAX_BYTES = 64 * 1024 * 1024
#: Bytes of a training log or named-column CSV given to ``koopman_train --logs`` (a 612 s
#: identification drive logs about 40 MB).
LOG_FILE_MAX_BYTES = 512 * 1024 * 1024


def csv_number(cell: str) -> float:
    """A number of a CSV input file (path files, excitation tables) as both ECUs read it:
    Python's ``float`` of an ASCII cell without underscores (decimal, ``inf`` or ``nan``,
    blanks around it). CSV is not TOML: ``1_0`` is refused, as the C ECU's ``strtod``
    refuses it, where ``float`` would read 10; so are non-ASCII digits and blanks, which the
    C ECU, reading bytes, does not take either.

    Raises:
        ValueError: ``cell`` is not such a number.
    """
    if "_" in cell or not cell.isascii():
        raise ValueError(f"not a number: {cell!r}")
    return float(cell)


class InputFileError(ValueError):
    """An input file breaks a size rule; the message names the file, the line and the rule."""


def bounded_lines(path: Path, max_bytes: int, error: type[Exception] = InputFileError) -> Iterator[str]:
    """The lines of a UTF-8 text file with their ends, each checked as it is read.

    Raises:
        error: ``FILE: line N: holds a NUL byte``, ``FILE: line N: longer than 4096
            bytes``, ``FILE: larger than M bytes (the limit of this file)`` or ``FILE: line
            N: not UTF-8``; OSError from opening or reading.
    """
    total = 0
    with Path(path).open("rb") as handle:
        for number, raw in enumerate(iter(lambda: handle.readline(MAX_LINE_BYTES + 1), b""), start=1):
            total += len(raw)
            if b"\0" in raw:
                raise error(f"{path}: line {number}: holds a NUL byte")
            if len(raw) > MAX_LINE_BYTES:
                raise error(f"{path}: line {number}: longer than {MAX_LINE_BYTES} bytes")
            if total > max_bytes:
                raise error(f"{path}: larger than {max_bytes} bytes (the limit of this file)")
            try:
                yield raw.decode("utf-8")
            except UnicodeDecodeError:
                raise error(f"{path}: line {number}: not UTF-8") from None


def read_bounded(path: Path, max_bytes: int, error: type[Exception] = InputFileError) -> bytes:
    """The bytes of a file of at most ``max_bytes``; at most ``max_bytes + 1`` are read.

    Raises:
        error: ``FILE: larger than M bytes (the limit of this file)``; OSError from
            opening or reading.
    """
    with Path(path).open("rb") as handle:
        data = handle.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes (the limit of this file)")
    return data


def check_file_size(path: Path, max_bytes: int, error: type[Exception] = InputFileError) -> None:
    """Before a reader that takes a file whole: a regular file of at most ``max_bytes``.

    Raises:
        error: ``FILE: not a regular file`` or ``FILE: larger than M bytes (the limit of
            this file)``; OSError from ``stat``.
    """
    info = Path(path).stat()
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{path}: not a regular file")
    if info.st_size > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes (the limit of this file)")

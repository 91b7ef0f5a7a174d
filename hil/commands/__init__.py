"""Subcommands of ``eso-hil`` (``python -m hil``): one module each, registered in
``hil.__main__``.

A subcommand module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``main(args) -> int`` (the exit status). The helpers here keep the subcommands alike:
the ``--dbc`` option, warnings printed once on stderr, progress bars on stderr, the
controller name checked before anything starts.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

_T = TypeVar("_T")

#: Warnings already printed by this process (each is printed once).
_warned: set[str] = set()


def warn(text: str) -> None:
    """``warning: text`` on stderr, once per distinct text."""
    if text in _warned:
        return
    _warned.add(text)
    print(f"warning: {text}", file=sys.stderr)


def add_dbc_option(parser: argparse.ArgumentParser, what: str) -> None:
    """``--dbc FILE``: how the log is decoded and shown (``what``), never what an ECU uses."""
    parser.add_argument("--dbc", type=Path, default=None, metavar="FILE",
                        help=f"CAN database to {what} (default: the project's "
                             "can_defs/vehicle.dbc; any format cantools reads)")


def add_ecu_input_options(parser: argparse.ArgumentParser, default: str = "") -> None:
    """``--model`` and ``--excite``: the ECU's own options of the same names (``eso-ecu``),
    which decide its commands; ``default`` says what a run without them uses."""
    parser.add_argument("--model", type=Path, default=None, metavar="PATH",
                        help="the ECU's --model: another Koopman artefact (eso-dkmpc, dkmpc) or a "
                             f"fitted bicycle (lmpc, lmpc-eso){default}")
    parser.add_argument("--excite", default=None, metavar="PROGRAM",
                        help="the ECU's --excite: identification excitation (chirp, prbs, steps, "
                             f"prbs-torque or a program file; docs/identification.md){default}")


def add_quiet_option(parser: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress bar (it is off anyway when stderr is not a terminal)."""
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bar (none is shown when stderr is not a terminal)")


#: Logs shorter than this many frames get no progress bar (they take well under a second).
PROGRESS_MIN_FRAMES = 2000


def progress(items: Iterable[_T], total: int, description: str, quiet: bool) -> Iterator[_T]:
    """``items`` with a tqdm progress bar on stderr, for long logs only: off with
    ``quiet``, when stderr is not a terminal (a pipe, a file, CI) or below
    :data:`PROGRESS_MIN_FRAMES` frames."""
    if quiet or total < PROGRESS_MIN_FRAMES or not sys.stderr.isatty():
        yield from items
        return
    from tqdm import tqdm

    with tqdm(items, total=total, desc=description, unit="frame", file=sys.stderr,
              leave=False, dynamic_ncols=True) as bar:
        yield from bar


def controller_name(text: str, source: str = "--controller") -> str:
    """The registry name of a controller given in any case (``LMPC`` -> ``lmpc``).

    Raises:
        hil.errors.HilError: not a registry name (the message lists them).
    """
    from controller.registry import ALL_CONTROLLER_NAMES
    from hil.errors import HilError

    name = text.strip().lower()
    if name not in ALL_CONTROLLER_NAMES:
        raise HilError(f"{source}: unknown controller {text!r}; choose one of "
                       f"{', '.join(ALL_CONTROLLER_NAMES)} (any case)")
    return name


def display_database(dbc: Path | None) -> tuple[Any, str]:
    """The cantools database of ``--dbc`` (None for the project's DBC) and its name."""
    from hil.decode_log import load_display_dbc

    database = load_display_dbc(dbc)
    return database, (dbc.name if database is not None and dbc is not None else "")

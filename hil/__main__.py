"""``eso-hil <subcommand> ...`` (``python -m hil``): the HIL's command line.

``eso-hil`` is the console command ``pip install`` / ``make setup`` puts into the
environment's ``bin`` folder (``[project.scripts]`` in pyproject.toml -> `entry`).

Subcommands are modules under ``hil/commands/``, listed in :data:`SUBCOMMANDS`; each
keeps its module-level imports light (argparse only) and imports its machinery in
``main``, so building the parser stays cheap. A new subcommand is a new module plus one
line in the table.

Errors of the project (``HilError`` and the other packages' bases) print ``error: ...``
on stderr and exit 1 (:data:`EXIT_ERROR`), a bad option value (``hil.errors.OptionError``)
exits 2 (:data:`EXIT_USAGE`, argparse's status for a bad option); ``--debug`` shows the
traceback instead. SIGINT, SIGTERM and SIGHUP all unwind the command the same way (ECU
stopped, log flushed, sidecar written) and exit 130, 143 and 129 (128 + the signal
number). A reader that closes the pipe early
(``eso-hil decode LOG | head``) ends the command quietly with 141 (128 + SIGPIPE), as a
C tool killed by SIGPIPE, not with a BrokenPipeError traceback.
"""
from __future__ import annotations

import os

# Before numpy loads (see firmware_sim/__main__.py): single-threaded BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
from types import ModuleType

#: Subcommand name -> module implementing it (``HELP``, ``add_arguments``, ``main``).
SUBCOMMANDS: dict[str, str] = {
    "run": "hil.commands.run",
    "replay": "hil.commands.replay",
    "decode": "hil.commands.decode",
    "play": "hil.commands.play",
    "faults": "hil.commands.faults",
}


#: Exit status of an error of the project (``error: ...``).
EXIT_ERROR = 1
#: Exit status of a bad option value, as argparse's own option errors and ``eso-ecu``'s.
EXIT_USAGE = 2


def _project_errors() -> tuple[type[BaseException], ...]:
    """Base exceptions of the packages a subcommand may surface (imported lazily)."""
    errors: list[type[BaseException]] = []
    for module, name in (("hil.errors", "HilError"), ("can_defs.errors", "CanDefsError"),
                         ("models.errors", "ModelError"), ("controller.errors", "ControllerError"),
                         ("firmware_sim.errors", "EcuError")):
        try:
            errors.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError):
            continue
    return tuple(errors)


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, ModuleType]]:
    """The top-level parser with every registered subcommand."""
    parser = argparse.ArgumentParser(prog="eso-hil",
                                     description="Hardware-in-the-loop emulation over CAN.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    subparsers = parser.add_subparsers(dest="subcommand", required=True, metavar="SUBCOMMAND")
    modules = {}
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        sub = subparsers.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(sub)
        modules[name] = module
    return parser, modules


def _raise_stop(signum: int, frame: object) -> None:
    from hil.errors import StopSignal
    raise StopSignal(signum)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen subcommand; returns the exit status."""
    parser, modules = build_parser()
    args = parser.parse_args(argv)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGHUP):
            previous[signum] = signal.signal(signum, _raise_stop)
    try:
        return int(modules[args.subcommand].main(args))
    except _project_errors() as e:
        if args.debug:
            raise
        from hil.errors import OptionError

        print(f"error: {e}", file=sys.stderr)
        return EXIT_USAGE if isinstance(e, OptionError) else EXIT_ERROR
    except KeyboardInterrupt as e:
        signum = getattr(e, "signum", signal.SIGINT)
        print(f"error: stopped by {signal.Signals(signum).name}", file=sys.stderr)
        return 128 + int(signum)
    except BrokenPipeError:
        return _closed_pipe()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


#: Exit status when the reader of stdout went away (128 + SIGPIPE).
EXIT_CLOSED_PIPE = 128 + 13


def _closed_pipe() -> int:
    """stdout's reader is gone: point stdout at /dev/null so the interpreter's final
    flush does not raise again, and exit as a SIGPIPE'd tool does."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return EXIT_CLOSED_PIPE


def entry() -> None:
    """The ``eso-hil`` console command: `main` plus a quiet end on a closed pipe (the
    last buffered output is flushed here, where a closed pipe can still be caught)."""
    status = main()
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        status = _closed_pipe()
    sys.exit(status)


if __name__ == "__main__":
    entry()

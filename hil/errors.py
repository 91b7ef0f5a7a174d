"""Exceptions of the ``hil`` package: one base, :class:`HilError`, for everything outside
the control loop (scenario files, path files, study runs, the HIL nodes).

Third-party errors (``tomllib``, ``OSError``, numpy parsing) are wrapped with
``raise ... from e`` so a CLI can print ``error: ...`` and exit non-zero.
"""
from __future__ import annotations


class HilError(Exception):
    """Base of every error raised by the ``hil`` package."""


class ScenarioError(HilError):
    """A scenario TOML file is missing, unreadable or has an invalid field (the message
    names the file, the field and the value)."""


class PathFileError(HilError):
    """A reference path CSV is missing, malformed or violates the contract (header
    ``x,y,yaw``, at most 0.5 m between points, driving order)."""


class MetricsError(HilError):
    """Inputs to a metric have the wrong shape or are not finite."""


class StudyError(HilError):
    """The closed-loop study could not run (unknown controller, missing plant, ...)."""


class OutputPathError(HilError):
    """An output file or folder cannot be used: it is one of the run's inputs, exists (without
    the command's replace option), or its folder is missing or not writable."""


class OptionError(HilError):
    """A command-line option has a value the command cannot use: an unknown name, a number
    out of range, an output it may not write (the message names the option and the value).
    ``eso-hil`` exits 2 for it, as for argparse's own option errors and as ``eso-ecu`` does;
    other errors exit 1."""


class StopSignal(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived: unwinds like Ctrl-C (SIGINT), so every ``finally`` stops
    the ECU, flushes the log and writes the sidecar; the command exits 128 + ``signum``."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

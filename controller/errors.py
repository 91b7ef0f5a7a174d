"""Exceptions of the controller package (raised at build/load time only, never in step())."""
from __future__ import annotations


class ControllerError(Exception):
    """Base class of every error the controller package raises."""


class TuningError(ControllerError):
    """A tuning file is missing, malformed or holds an out-of-range value (names field and value)."""


class PathError(ControllerError):
    """A reference path (CSV or arrays) is unusable; the message names file, row and reason."""


class UnknownControllerError(ControllerError):
    """``create_controller`` got a name outside ``CONTROLLER_NAMES``."""

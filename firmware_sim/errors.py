"""Exception hierarchy of firmware_sim.

Errors are raised only outside the control loop (start-up, configuration, CLI). Inside the
loop nothing raises: faults become mode events and FAULTS bits (see ``ecu.py``).
"""
from __future__ import annotations


class EcuError(Exception):
    """Base class of every error raised on purpose by firmware_sim."""


class ConfigError(EcuError):
    """An ECU setting is invalid; the message names the setting and the value."""


class PathArgumentError(EcuError):
    """A ``--path ID=FILE.csv`` argument is malformed, duplicated or names an unreadable file."""


class UnknownControllerError(EcuError):
    """The controller name is not one of the registry's names."""


class BusOpenError(EcuError):
    """The CAN bus could not be opened (wraps the python-can error)."""

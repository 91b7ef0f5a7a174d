"""Exception hierarchy of can_defs.

Everything raised on purpose by this package derives from `CanDefsError`, so a node can
catch one class at the boundary of its RX/TX code. Third-party (cantools) errors are
wrapped with ``raise ... from e``.
"""
from __future__ import annotations


class CanDefsError(Exception):
    """Base class of every error raised by can_defs."""


class DbcLoadError(CanDefsError):
    """The DBC file could not be read or does not describe the frames the codec expects."""


class EncodeError(CanDefsError):
    """A frame cannot be encoded: non-finite value, wrong type, undefined choice value or
    alive counter outside 0..15. The message names the frame, the field and the value."""


class DecodeError(CanDefsError):
    """A payload cannot be decoded into a typed frame."""


class UnknownFrameError(DecodeError):
    """The arbitration ID is not one of the contract's frames."""


class FrameLengthError(DecodeError):
    """The payload is not 8 bytes long."""


class UndefinedValueError(DecodeError):
    """A choice signal (CTRL_MODE, QP_STATUS) carries a raw value with no defined name."""

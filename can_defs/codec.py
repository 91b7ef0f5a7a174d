"""Encode typed frames to 8-byte payloads and back, on cantools and the contract's DBC.

The DBC is parsed once (first use); each frame class gets a `_FrameCodec` holding its
cantools message and, per field, the signal name, the Python kind and the representable
range, so a call only converts values, calls cantools and patches the CRC.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any

import cantools

from can_defs.crc import e2e_crc
from can_defs.dbc import load_database
from can_defs.errors import (DbcLoadError, EncodeError, FrameLengthError,
                             UndefinedValueError, UnknownFrameError)
from can_defs.frames import (FRAME_CLASSES, FRAME_LENGTH, HIL_FRAME_IDS, Frame, FrameId)

CRC_SIGNAL = "CRC"
COUNTER_SIGNAL = "CNT"
COUNTER_MODULUS = 16

_FLOAT, _INT, _BOOL, _ENUM = "float", "int", "bool", "enum"


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """A received payload: the typed frame with physical values, its alive counter
    (None for HIL frames) and whether its CRC matched (always True for HIL frames, which
    carry none). Decoding does not apply the counter rules: that is `E2EReceiver`'s job."""

    frame: Frame
    counter: int | None
    crc_ok: bool


@dataclass(frozen=True, slots=True)
class _FieldCodec:
    """How one dataclass field maps onto its DBC signal."""

    field_name: str
    signal_name: str
    kind: str
    minimum: float | int
    maximum: float | int
    enum_type: type[IntEnum] | None


class _FrameCodec:
    """Encoder/decoder of one frame type; built once from the DBC."""

    def __init__(self, frame_class: type, message: cantools.database.can.Message) -> None:
        self.frame_class = frame_class
        self.frame_id: FrameId = frame_class.FRAME_ID
        self.message = message
        self.e2e = self.frame_id not in HIL_FRAME_IDS
        hints = typing.get_type_hints(frame_class)
        signals = {signal.name: signal for signal in message.signals}
        fields = []
        for field in dataclasses.fields(frame_class):
            signal_name = field.name.upper()
            signal = signals.get(signal_name)
            if signal is None:
                raise DbcLoadError(
                    f"DBC message {message.name} has no signal {signal_name} "
                    f"for field {frame_class.__name__}.{field.name}")
            fields.append(_field_codec(field.name, signal, hints[field.name], message.name))
        self.fields: tuple[_FieldCodec, ...] = tuple(fields)
        expected = {f.signal_name for f in fields}
        if self.e2e:
            expected |= {CRC_SIGNAL, COUNTER_SIGNAL}
        if expected != set(signals):
            raise DbcLoadError(
                f"DBC message {message.name} has signals {sorted(signals)}, "
                f"the codec expects {sorted(expected)}")

    def encode(self, frame: Frame, counter: int) -> bytes:
        """8-byte payload of `frame` with alive counter `counter` (E2E frames only)."""
        values: dict[str, int | float] = {}
        for field in self.fields:
            values[field.signal_name] = _to_raw_physical(
                field, getattr(frame, field.field_name), self.message.name)
        if self.e2e:
            values[CRC_SIGNAL] = 0
            values[COUNTER_SIGNAL] = counter
        try:
            payload = self.message.encode(values, scaling=True, padding=False, strict=True)
        except (cantools.database.EncodeError, TypeError, ValueError) as error:
            # Unreachable after saturation unless the DBC and the dataclasses disagree.
            raise EncodeError(f"{self.message.name}: {error}") from error
        if self.e2e:
            crc = e2e_crc(self.frame_id, payload)
            payload = bytes((crc,)) + payload[1:]
        return bytes(payload)

    def decode(self, data: bytes) -> DecodedFrame:
        """Typed frame of an 8-byte payload (length checked by the caller)."""
        signals = self.message.decode(data, decode_choices=False, scaling=True)
        kwargs: dict[str, Any] = {}
        for field in self.fields:
            value = signals[field.signal_name]
            if field.kind == _FLOAT:
                kwargs[field.field_name] = float(value)
            elif field.kind == _INT:
                kwargs[field.field_name] = int(value)
            elif field.kind == _BOOL:
                kwargs[field.field_name] = bool(value)
            else:
                assert field.enum_type is not None
                try:
                    kwargs[field.field_name] = field.enum_type(value)
                except ValueError as error:
                    raise UndefinedValueError(
                        f"{self.message.name}.{field.signal_name}: raw value {value} has no "
                        f"{field.enum_type.__name__} name") from error
        frame = self.frame_class(**kwargs)
        if not self.e2e:
            return DecodedFrame(frame=frame, counter=None, crc_ok=True)
        return DecodedFrame(frame=frame, counter=int(signals[COUNTER_SIGNAL]),
                            crc_ok=signals[CRC_SIGNAL] == e2e_crc(self.frame_id, data))


def _field_codec(field_name: str, signal: Any, hint: Any, message_name: str) -> _FieldCodec:
    """Kind and range of one field, cross-checked against its DBC signal."""
    enum_type = None
    if isinstance(hint, type) and issubclass(hint, IntEnum):
        kind, enum_type = _ENUM, hint
        names = {int(value): str(name) for value, name in (signal.choices or {}).items()}
        expected = {member.value: member.name for member in hint}
        if names != expected:
            raise DbcLoadError(f"DBC {message_name}.{signal.name} choices {names} differ "
                               f"from {hint.__name__} {expected}")
    elif hint is bool:
        kind = _BOOL
    elif hint is int:
        kind = _INT
    elif hint is float:
        kind = _FLOAT
    else:
        raise DbcLoadError(f"unsupported field type {hint!r} for {message_name}.{signal.name}")
    if signal.minimum is None or signal.maximum is None:
        raise DbcLoadError(f"DBC {message_name}.{signal.name} has no [min|max] range")
    minimum, maximum = signal.minimum, signal.maximum
    if kind in (_INT, _BOOL, _ENUM):
        minimum, maximum = int(minimum), int(maximum)
    return _FieldCodec(field_name, signal.name, kind, minimum, maximum, enum_type)


def _to_raw_physical(field: _FieldCodec, value: Any, message_name: str) -> int | float:
    """Physical value ready for cantools: type-checked, finite, saturated to the signal's
    representable range (the contract makes saturation the sender's job)."""
    kind = field.kind
    if kind == _FLOAT or kind == _INT:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            # Slow path for numpy scalars and other numbers; bools and strings are refused
            # so that a swapped argument does not go out as a plausible value.
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise EncodeError(f"{message_name}.{field.signal_name}: expected a number, "
                                  f"got {value!r}")
            value = int(value) if isinstance(value, numbers.Integral) else float(value)
        if isinstance(value, float):
            if not math.isfinite(value):
                raise EncodeError(f"{message_name}.{field.signal_name}: non-finite value {value}")
            if kind == _INT:
                value = round(value)
        if value < field.minimum:
            return field.minimum
        if value > field.maximum:
            return field.maximum
        return value
    if kind == _BOOL:
        try:
            if value == 0 or value == 1:
                return 1 if value else 0
        except (TypeError, ValueError):  # e.g. an array: truth value is ambiguous
            pass
        raise EncodeError(f"{message_name}.{field.signal_name}: expected a bool, got {value!r}")
    assert field.enum_type is not None
    try:
        return int(field.enum_type(value))
    except (TypeError, ValueError) as error:
        raise EncodeError(f"{message_name}.{field.signal_name}: {value!r} is not a "
                          f"{field.enum_type.__name__}") from error


_CODECS: dict[int, _FrameCodec] = {}
_CODECS_BY_CLASS: dict[type, _FrameCodec] = {}


def prepare(dbc_path: str | Path | None = None) -> None:
    """Parse the DBC and build the frame codecs now rather than at the first `encode` /
    `decode` (a node calls this at start-up, before it opens the bus, so that a DBC it
    cannot use stops it there and the ~0.1 s parse stays off its first cycle).

    ``dbc_path``: a DBC other than the contract's (``can_defs/vehicle.dbc``); the codecs
    of this process are then built from it. Raises `DbcLoadError` if the DBC cannot be
    read or parsed, or if it and the frame classes disagree (the codecs in use are kept).
    """
    if dbc_path is None:
        _codecs()
        return
    built = _build_codecs(load_database(Path(dbc_path)))
    _CODECS.clear()
    _CODECS_BY_CLASS.clear()
    _install(built)


def _build_codecs(database: cantools.database.can.Database) -> dict[int, _FrameCodec]:
    """One codec per contract frame of ``database``; raises `DbcLoadError` on a mismatch."""
    built = {}
    for frame_id, frame_class in FRAME_CLASSES.items():
        try:
            message = database.get_message_by_frame_id(int(frame_id))
        except KeyError as error:
            raise DbcLoadError(f"DBC has no frame {frame_id.name} (0x{frame_id:03X})") from error
        if message.length != FRAME_LENGTH or message.name != frame_id.name:
            raise DbcLoadError(f"DBC frame 0x{frame_id:03X} is {message.name} with "
                               f"length {message.length}, expected {frame_id.name}, 8")
        built[int(frame_id)] = _FrameCodec(frame_class, message)
    return built


def _install(built: dict[int, _FrameCodec]) -> None:
    _CODECS_BY_CLASS.update({codec.frame_class: codec for codec in built.values()})
    _CODECS.update(built)


def _codecs() -> dict[int, _FrameCodec]:
    """Frame codecs by arbitration ID, built from the DBC on first use."""
    if not _CODECS:
        _install(_build_codecs(load_database()))
    return _CODECS


def encode(frame: Frame, counter: int = 0) -> bytes:
    """8-byte payload of `frame`.

    Physical values outside a signal's representable range are saturated to it; E2E
    frames get CNT = `counter` (0..15) and their CRC; HIL frames carry neither and ignore
    `counter`. Raises `EncodeError` for NaN/inf, a wrong type, an undefined CtrlMode /
    QpStatus value or a counter outside 0..15.
    """
    if not _CODECS:
        _codecs()
    codec = _CODECS_BY_CLASS.get(type(frame))
    if codec is None:
        raise EncodeError(f"not a contract frame: {type(frame).__name__}")
    if isinstance(counter, bool) or not isinstance(counter, int) or not 0 <= counter < COUNTER_MODULUS:
        raise EncodeError(f"{codec.message.name}: alive counter must be an int in 0..15, "
                          f"got {counter!r}")
    return codec.encode(frame, counter)


def decode(arbitration_id: int, data: bytes) -> DecodedFrame:
    """Typed frame, alive counter and CRC verdict of a received payload.

    Raises `UnknownFrameError` for an ID outside the contract, `FrameLengthError` when
    `data` is not 8 bytes, `UndefinedValueError` for a CTRL_MODE / QP_STATUS raw value
    without a name. A wrong CRC is reported (`crc_ok=False`), not raised.
    """
    codec = _codecs().get(arbitration_id) if isinstance(arbitration_id, int) else None
    if codec is None:
        raise UnknownFrameError(f"unknown arbitration ID {arbitration_id!r}")
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise FrameLengthError(f"{codec.message.name}: payload must be bytes, got "
                               f"{type(data).__name__}")
    if len(data) != FRAME_LENGTH:
        raise FrameLengthError(f"{codec.message.name}: payload of {len(data)} bytes, "
                               f"expected {FRAME_LENGTH}")
    return codec.decode(bytes(data))


class FrameSender:
    """Alive counters of one transmitting node: one per frame ID, starting at 0 and
    advanced +1 mod 16 by every `encode` of that frame (HIL frames have no counter)."""

    def __init__(self) -> None:
        self._counters: dict[FrameId, int] = {}

    def next_counter(self, frame_id: int) -> int:
        """CNT the next `encode` of `frame_id` will send."""
        return self._counters.get(FrameId(frame_id), 0)

    def encode(self, frame: Frame) -> bytes:
        """Payload of `frame` with this sender's next alive counter for its ID."""
        frame_id = getattr(type(frame), "FRAME_ID", None)
        if frame_id is None or frame_id in HIL_FRAME_IDS:  # encode() names a non-frame
            return encode(frame)
        counter = self._counters.get(frame_id, 0)
        payload = encode(frame, counter)
        # Advance only once the frame was really encoded, so a refused frame leaves no gap.
        self._counters[frame_id] = (counter + 1) % COUNTER_MODULUS
        return payload

    def reset(self) -> None:
        """Restart every counter at 0 (a node restart)."""
        self._counters.clear()

"""Frames as a faulty sender makes them, for the fault injection: a standard-ID data frame
(`standard_frame`), the same frame with fields rewritten and its counter moved on, CRC
recomputed (`rewrite_frame`), a look-alike of another frame kind with the same ID number
(`lookalike`, contract rev. 2), and what one fault did (`FaultRecord`).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import can

from can_defs.codec import decode, encode
from can_defs.frames import FRAME_LENGTH, FrameId
from hil.faults import LOOKALIKE_KINDS


@dataclass
class FaultRecord:
    """What one fault did: frames it acted on and the first tick it acted (ms)."""

    description: str
    actions: int = 0
    first_action_ms: int | None = None

    def note(self, tick_ms: int, count: int = 1) -> None:
        self.actions += count
        if self.first_action_ms is None:
            self.first_action_ms = tick_ms


def standard_frame(frame_id: int, data: bytes) -> can.Message:
    """A data frame with an 11-bit ID (as the HIL nodes send them)."""
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def rewrite_frame(message: can.Message, change: Mapping[str, Any], counter_step: int = 0) -> can.Message:
    """Same frame with fields replaced and the counter moved on by ``counter_step``, CRC
    recomputed (a faulty sender)."""
    decoded = decode(message.arbitration_id, bytes(message.data))
    frame = dataclasses.replace(decoded.frame, **change)
    return standard_frame(message.arbitration_id, encode(frame, ((decoded.counter or 0) + counter_step) % 16))


def lookalike(message: can.Message, frame_kind: str) -> can.Message:
    """``message`` as a frame of another kind with the same ID number (contract rev. 2: never
    a contract frame): fd / extended carry the frame with the next counter (CRC valid), a
    remote frame asks for 8 bytes and carries none, an error frame keeps the bytes."""
    flag = LOOKALIKE_KINDS[frame_kind]
    if frame_kind in ("fd", "extended"):
        data = bytes(rewrite_frame(message, {}, counter_step=1).data) \
            if message.arbitration_id != FrameId.HIL_SYNC else bytes(message.data)
    else:
        data = b"" if frame_kind == "remote" else bytes(message.data)
    flags = {"is_extended_id": False, flag: True}
    return can.Message(arbitration_id=message.arbitration_id, data=data, dlc=FRAME_LENGTH, **flags)

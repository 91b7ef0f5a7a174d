"""Playing a recorded log onto a CAN bus with its original timing, as ``can.player`` does.

- `select_ids`: keep only some arbitration IDs (``--ids``).
- `rewrite_e2e`: re-number the alive counter of every E2E-protected contract frame per ID
  (continuing from the first frame's counter, +1 mod 16) and recompute its CRC, so a
  spliced or edited log is a well-formed sequence that drives another ECU. HIL frames,
  frames outside the DBC and frames of the wrong length pass unchanged.
- `scale_timing`: play faster or slower (``--speed``).
- `play`: `can.MessageSync` paces the frames by their timestamps (or ignores them), with
  can.player's options: ``gap`` (minimum time between frames), ``skip`` (longest pause
  kept) and error frames left out unless asked for; each frame goes to the bus as a
  fresh message (no channel of the recording, no timestamp).
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import can

from can_defs.crc import e2e_crc
from can_defs.frames import E2E_FRAME_IDS, FRAME_LENGTH
from hil.errors import HilError
from hil.logio import is_contract_data_frame

COUNTER_MODULUS = 16
#: MessageSync does not sleep longer than this between two frames (s): a pause in the
#: recording longer than this is shortened (python-can's ``skip``).
DEFAULT_MAX_GAP_S = 60.0
#: Minimum time between two frames sent (s), as can.player's ``--gap`` default.
DEFAULT_MIN_GAP_S = 0.0001


class PlayError(HilError):
    """The log cannot be played (bad option value, bus send failure)."""


@dataclass
class RewriteStats:
    """What `rewrite_e2e` changed: frames re-numbered per ID and CRCs that were wrong."""

    renumbered: dict[int, int] = field(default_factory=dict)
    counters_changed: int = 0
    crcs_fixed: int = 0
    unchanged_wrong_length: int = 0


def select_ids(messages: Iterable[can.Message], ids: Sequence[int] | None) -> list[can.Message]:
    """The messages whose arbitration ID is in ``ids`` (all when None)."""
    if ids is None:
        return list(messages)
    wanted = set(ids)
    return [m for m in messages if not m.is_error_frame and m.arbitration_id in wanted]


def _copy(message: can.Message, data: bytes | None = None, timestamp: float | None = None) -> can.Message:
    return can.Message(
        timestamp=message.timestamp if timestamp is None else timestamp,
        arbitration_id=message.arbitration_id, is_extended_id=message.is_extended_id,
        is_remote_frame=message.is_remote_frame, is_error_frame=message.is_error_frame,
        dlc=message.dlc, is_fd=message.is_fd, bitrate_switch=message.bitrate_switch,
        data=bytes(message.data or b"") if data is None else data)


def rewrite_e2e(messages: Sequence[can.Message]) -> tuple[list[can.Message], RewriteStats]:
    """Re-number alive counters per ID and recompute CRCs (module docstring).

    Returns the new messages (the input is not modified) and what changed.
    """
    stats = RewriteStats()
    next_counter: dict[int, int] = {}
    rewritten = []
    for message in messages:
        frame_id = message.arbitration_id
        if not is_contract_data_frame(message) or frame_id not in E2E_FRAME_IDS:
            rewritten.append(_copy(message))
            continue
        if len(message.data) != FRAME_LENGTH:
            stats.unchanged_wrong_length += 1
            rewritten.append(_copy(message))
            continue
        data = bytearray(message.data)
        counter = next_counter.get(frame_id, data[1] & 0x0F)
        if data[1] & 0x0F != counter:
            stats.counters_changed += 1
        data[1] = (data[1] & 0xF0) | counter
        if message.data[0] != e2e_crc(frame_id, bytes(message.data)):
            stats.crcs_fixed += 1  # the recorded CRC was already wrong
        data[0] = e2e_crc(frame_id, bytes(data))
        next_counter[frame_id] = (counter + 1) % COUNTER_MODULUS
        stats.renumbered[frame_id] = stats.renumbered.get(frame_id, 0) + 1
        rewritten.append(_copy(message, data=bytes(data)))
    return rewritten, stats


def scale_timing(messages: Sequence[can.Message], speed: float) -> list[can.Message]:
    """Copies whose time since the first frame is divided by ``speed`` (> 0)."""
    if not speed > 0:
        raise PlayError(f"--speed must be > 0, got {speed}")
    if not messages:
        return []
    start = messages[0].timestamp
    return [_copy(m, timestamp=start + (m.timestamp - start) / speed) for m in messages]


def play(messages: Iterable[can.Message], bus: can.BusABC, *, max_gap_s: float = DEFAULT_MAX_GAP_S,
         min_gap_s: float = DEFAULT_MIN_GAP_S, timestamps: bool = True,
         error_frames: bool = False,
         on_sent: Callable[[int, can.Message], None] | None = None) -> int:
    """Send ``messages`` on ``bus`` with the time between them as recorded (``timestamps``
    False: back to back, ``min_gap_s`` apart); error frames only with ``error_frames``
    (as can.player); returns the number sent.

    Raises:
        PlayError: the bus refused a frame.
    """
    sent = 0
    for message in can.MessageSync(messages, timestamps=timestamps, gap=min_gap_s,
                                   skip=max_gap_s):
        if message.is_error_frame and not error_frames:
            continue
        outgoing = _copy(message, timestamp=0.0)
        try:
            bus.send(outgoing)
        except (can.CanError, OSError, ValueError) as error:
            raise PlayError(f"the bus refused frame {sent + 1} (0x{message.arbitration_id:03X}): "
                            f"{error}") from error
        sent += 1
        if on_sent is not None:
            on_sent(sent, message)
    return sent


def parse_ids(text: str, names: Mapping[str, int] | None = None) -> list[int]:
    """``"0x100,0x101,256"`` -> [0x100, 0x101, 0x100]: hex with 0x, else decimal; message
    names are accepted too: the contract's (``VEH_DYN``), or those of ``names`` (name ->
    ID, from ``--dbc``), case-insensitive."""
    from can_defs.frames import FrameId

    known = {name.upper(): int(fid) for name, fid in FrameId.__members__.items()} \
        if names is None else {name.upper(): fid for name, fid in names.items()}
    ids = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        if item.upper() in known:
            ids.append(known[item.upper()])
            continue
        try:
            value = int(item, 0)
        except ValueError:
            raise PlayError(f"--ids: {item!r} is neither an ID (0x100, 256) nor a message "
                            "name of the DBC") from None
        if not 0 <= value <= 0x1FFFFFFF:
            raise PlayError(f"--ids: {item!r} is outside 0..0x1FFFFFFF")
        ids.append(value)
    if not ids:
        raise PlayError("--ids: no ID given")
    return ids

"""Receiver side of the E2E protection (docs/can-contract.md, "End-to-end protection").

Pure logic: no clock, no bus, no cantools. `check` never raises on any payload; it
classifies each frame and says whether the receiver may use it. What to do next (hold,
predict, degrade) is the node's fault reaction, not this module's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from can_defs.crc import e2e_crc
from can_defs.errors import UnknownFrameError
from can_defs.frames import FRAME_LENGTH, HANDSHAKE_TICK, HIL_FRAME_IDS, TICK_STEP_MS, FrameId

COUNTER_MODULUS = 16
MAX_TOLERATED_LOST = 2
"""A counter jump of 2 or 3 (1 or 2 frames lost) is still accepted."""


class E2EStatus(Enum):
    """Verdict on one received frame."""

    OK = "ok"
    CRC_ERROR = "crc_error"
    REPEATED = "repeated"
    LOST = "lost"
    SEQUENCE_ERROR = "sequence_error"
    WRONG_LENGTH = "wrong_length"
    UNKNOWN_ID = "unknown_id"
    BAD_TICK = "bad_tick"

    @property
    def is_e2e_error(self) -> bool:
        """True for the statuses the contract counts as E2E errors (frame discarded):
        CRC_ERROR, REPEATED, SEQUENCE_ERROR, WRONG_LENGTH, BAD_TICK. OK and LOST are
        accepted frames; UNKNOWN_ID is foreign traffic, not an error of a contract frame."""
        return self in _E2E_ERRORS


_E2E_ERRORS = frozenset({E2EStatus.CRC_ERROR, E2EStatus.REPEATED, E2EStatus.SEQUENCE_ERROR,
                         E2EStatus.WRONG_LENGTH, E2EStatus.BAD_TICK})


@dataclass(frozen=True, slots=True)
class E2EResult:
    """Verdict on one frame: `status`, frames counted as lost before it (`lost`: 1 or 2
    for LOST, jump - 1 for SEQUENCE_ERROR, else 0) and whether the receiver may use the
    frame (`accepted`: OK and LOST)."""

    status: E2EStatus
    lost: int
    accepted: bool


_OK = E2EResult(E2EStatus.OK, 0, True)
_CRC_ERROR = E2EResult(E2EStatus.CRC_ERROR, 0, False)
_REPEATED = E2EResult(E2EStatus.REPEATED, 0, False)
_WRONG_LENGTH = E2EResult(E2EStatus.WRONG_LENGTH, 0, False)
_UNKNOWN_ID = E2EResult(E2EStatus.UNKNOWN_ID, 0, False)
_BAD_TICK = E2EResult(E2EStatus.BAD_TICK, 0, False)
_LOST = {lost: E2EResult(E2EStatus.LOST, lost, True) for lost in range(1, MAX_TOLERATED_LOST + 1)}
_SEQUENCE_ERROR = {lost: E2EResult(E2EStatus.SEQUENCE_ERROR, lost, False)
                   for lost in range(MAX_TOLERATED_LOST + 1, COUNTER_MODULUS - 1)}

_BYTES_LIKE = (bytes, bytearray, memoryview)


@dataclass(slots=True)
class E2EStats:
    """Running counts of one receiver (or of a whole monitor): frames per status and the
    total of frames counted as lost."""

    counts: dict[E2EStatus, int] = field(default_factory=lambda: dict.fromkeys(E2EStatus, 0))
    lost: int = 0

    def record(self, result: E2EResult) -> None:
        """Count one verdict."""
        self.counts[result.status] += 1
        self.lost += result.lost

    @property
    def e2e_errors(self) -> int:
        """Frames discarded as E2E errors (see `E2EStatus.is_e2e_error`)."""
        return sum(count for status, count in self.counts.items() if status.is_e2e_error)

    @property
    def total(self) -> int:
        """Frames checked."""
        return sum(self.counts.values())


class E2EReceiver:
    """E2E state of one received frame ID: length, CRC and alive counter for protected
    frames; length and TICK for HIL_SYNC / HIL_SYNC_ACK.

    The first frame with a good CRC synchronises the counter and is accepted; after a
    SEQUENCE_ERROR the next good frame re-synchronises the same way.
    """

    def __init__(self, frame_id: int) -> None:
        try:
            self.frame_id = FrameId(frame_id)
        except ValueError as error:
            raise UnknownFrameError(f"no E2E receiver for unknown frame ID {frame_id!r}") from error
        self._protected = self.frame_id not in HIL_FRAME_IDS
        self._last_counter: int | None = None
        self.stats = E2EStats()

    @property
    def synchronised(self) -> bool:
        """True once a counter reference is held (never for HIL frames)."""
        return self._last_counter is not None

    @property
    def last_counter(self) -> int | None:
        """Counter of the last accepted frame, None until (re-)synchronised."""
        return self._last_counter

    def reset(self) -> None:
        """Forget the counter reference (the next good frame synchronises); stats kept."""
        self._last_counter = None

    def check(self, data: bytes) -> E2EResult:
        """Classify one received payload and update the counter reference and stats.
        Never raises; anything that is not a byte string counts as WRONG_LENGTH."""
        result = self._classify(data)
        self.stats.record(result)
        return result

    def _classify(self, data: bytes) -> E2EResult:
        if isinstance(data, memoryview):
            data = data.tobytes()  # a view of any item format -> plain bytes 0..255
        if not isinstance(data, _BYTES_LIKE) or len(data) != FRAME_LENGTH:
            return _WRONG_LENGTH
        if not self._protected:
            tick = int.from_bytes(data[0:4], "little")
            if tick % TICK_STEP_MS == 0 or tick == HANDSHAKE_TICK:
                return _OK
            return _BAD_TICK
        if data[0] != e2e_crc(self.frame_id, data):
            return _CRC_ERROR
        counter = data[1] & 0x0F
        last = self._last_counter
        if last is None:
            self._last_counter = counter
            return _OK
        jump = (counter - last) % COUNTER_MODULUS
        if jump == 1:
            self._last_counter = counter
            return _OK
        if jump == 0:
            return _REPEATED
        if jump <= MAX_TOLERATED_LOST + 1:
            self._last_counter = counter
            return _LOST[jump - 1]
        # Too many frames missing to trust the sequence: drop this one and let the next
        # good frame re-synchronise.
        self._last_counter = None
        return _SEQUENCE_ERROR[jump - 1]


class E2EMonitor:
    """One `E2EReceiver` per contract frame ID; foreign IDs are classified UNKNOWN_ID.

    `stats` aggregates every verdict, UNKNOWN_ID included.
    """

    def __init__(self) -> None:
        self._receivers: dict[int, E2EReceiver] = {int(fid): E2EReceiver(fid) for fid in FrameId}
        self.stats = E2EStats()

    @property
    def receivers(self) -> dict[FrameId, E2EReceiver]:
        """Receiver of every contract frame ID (a copy of the mapping)."""
        return {receiver.frame_id: receiver for receiver in self._receivers.values()}

    def receiver(self, frame_id: int) -> E2EReceiver:
        """Receiver of one contract frame ID; `UnknownFrameError` for others."""
        receiver = self._receivers.get(frame_id) if isinstance(frame_id, int) else None
        if receiver is None:
            raise UnknownFrameError(f"no E2E receiver for unknown frame ID {frame_id!r}")
        return receiver

    def check(self, arbitration_id: int, data: bytes) -> E2EResult:
        """Classify one received frame by its arbitration ID. Never raises."""
        receiver = self._receivers.get(arbitration_id) if isinstance(arbitration_id, int) else None
        result = _UNKNOWN_ID if receiver is None else receiver.check(data)
        self.stats.record(result)
        return result

    def reset(self) -> None:
        """Forget every counter reference (stats kept)."""
        for receiver in self._receivers.values():
            receiver.reset()

"""Bus wrappers: faults of the time base and of the ECU's own bus.

Two faults of the contract's revision 2 cannot be frames of the HIL nodes, so they are bus
wrappers for a run that drives the ECU itself (the fault campaign's ECU-level cases,
hil/fault_cases/python_ecu.py and hil/fault_cases/c_ecu.py): a jump of virtual time
(`TimeShiftingBus`, between the time master and the bus) and a lost bus (`LosableBus`,
between the ECU and the bus).
"""
from __future__ import annotations

from collections.abc import Callable

import can

from can_defs.codec import encode
from can_defs.frames import FRAME_LENGTH, HANDSHAKE_TICK, FrameId, HilSync
from hil.fault_frames import FaultRecord, standard_frame


class TimeShiftingBus:
    """The time master's bus with virtual time jumping ahead: from master TICK
    ``from_tick_ms`` on, every HIL_SYNC goes out with TICK + ``ahead_ms`` and every
    HIL_SYNC_ACK of such a TICK comes back as the master's TICK, so the master and the
    plant run on while the ECU sees its clock jump once (contract rev. 2, "jump of
    virtual time"). The handshake passes unchanged.

    Args:
        bus: the master's open bus (shut down with this wrapper).
        from_tick_ms: first master TICK sent shifted (ms, a multiple of 5).
        ahead_ms: how far the ECU's clock jumps (ms, a multiple of 5).
    """

    def __init__(self, bus: can.BusABC, from_tick_ms: int, ahead_ms: int) -> None:
        self.bus = bus
        self.from_tick_ms = from_tick_ms
        self.ahead_ms = ahead_ms
        self.record = FaultRecord(f"HIL_SYNC {ahead_ms / 1000:g} s ahead from "
                                  f"{from_tick_ms / 1000:g} s on (virtual time jumps once)")

    @staticmethod
    def _tick(message: can.Message, frame_id: FrameId) -> int | None:
        if (message.arbitration_id != frame_id or message.is_extended_id
                or len(message.data) != FRAME_LENGTH):
            return None
        return int.from_bytes(bytes(message.data[0:4]), "little")

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        """Send, HIL_SYNC of a TICK at or after ``from_tick_ms`` shifted ahead."""
        tick = self._tick(message, FrameId.HIL_SYNC)
        if tick is not None and tick != HANDSHAKE_TICK and tick >= self.from_tick_ms:
            self.record.note(tick)
            message = standard_frame(int(FrameId.HIL_SYNC), encode(HilSync(tick + self.ahead_ms)))
        self.bus.send(message, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Receive, an ACK of a shifted TICK shifted back to the master's TICK."""
        message = self.bus.recv(timeout)
        tick = None if message is None else self._tick(message, FrameId.HIL_SYNC_ACK)
        if tick is not None and tick != HANDSHAKE_TICK and tick >= self.from_tick_ms + self.ahead_ms:
            data = bytearray(message.data)
            data[0:4] = (tick - self.ahead_ms).to_bytes(4, "little")
            message = standard_frame(int(FrameId.HIL_SYNC_ACK), bytes(data))
        return message

    def shutdown(self) -> None:
        self.bus.shutdown()


class BusDownError(can.CanOperationError):
    """What a lost bus raises on every receive and send (an interface that went down)."""


class LosableBus:
    """The ECU's bus that can go away: after `lose`, every receive and send raises
    `BusDownError` (as python-can's SocketCAN bus does when the interface goes down), and
    the receive calls made meanwhile are counted (a busy loop shows as thousands).

    Args:
        bus: the ECU's open bus (shut down with this wrapper).
    """

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.lost = False
        self.calls_while_lost = 0

    def lose(self) -> None:
        """From now on the bus is gone."""
        self.lost = True

    def _check(self) -> None:
        if self.lost:
            self.calls_while_lost += 1
            raise BusDownError("CAN interface down (fault injection: lost bus)")

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self._check()
        return self.bus.recv(timeout)

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        self._check()
        self.bus.send(message, timeout)

    def shutdown(self) -> None:
        self.bus.shutdown()


def time_jump_wrapper(fault: dict, onset_ms: int,
                      made: list[TimeShiftingBus]) -> Callable[[can.BusABC], can.BusABC]:
    """A ``hil.rig.RigHooks.wrap_master_bus`` for an ECU-level fault case (``fault``, its
    ``kind`` and ``ahead_ms``): a jump of virtual time at ``onset_ms`` for ``time_jump``,
    the bus as it is otherwise; the wrapper it made goes into ``made`` (its record counts
    the frames it changed)."""
    def wrap(bus: can.BusABC) -> can.BusABC:
        if fault["kind"] != "time_jump":
            return bus
        made.append(TimeShiftingBus(bus, onset_ms, fault["ahead_ms"]))
        return made[-1]

    return wrap

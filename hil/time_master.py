"""Time masters of the HIL: lockstep (virtual time, deterministic) and real time (wall
clock), both driving the same nodes (plant, planner, frame monitors).

A node is anything with ``frames_due(tick_ms)``, ``receive(message, tick_ms)`` and
``advance(tick_ms, dt_s)`` (see `HilNode`). Both masters use a base tick of 5 ms, the
greatest common divisor of the contract's periods (10 ms plant, 25 ms planner and ECU).

Lockstep, exactly as docs/can-contract.md "Timing semantics" says:

1. Handshake: HIL_SYNC with TICK = 0xFFFFFFFF every 100 ms of wall clock until the ECU
   answers HIL_SYNC_ACK with TICK = 0xFFFFFFFF (it does so once ready); give up after
   ``handshake_timeout_s`` with `HandshakeTimeoutError`.
2. Each tick t = 0, 5, 10, ... ms: send every node frame due at t (state at t), then
   HIL_SYNC with TICK = t; wait for HIL_SYNC_ACK with TICK = t, handing every frame
   received meanwhile to the nodes (`AckTimeoutError` names the tick otherwise); then
   the nodes advance: the plant applies the newest valid STEER_TORQUE_CMD and integrates
   from t to t + 5 ms.

Real time: the same tick sequence on a monotonic clock with absolute deadlines
(``next += period``, so lateness never accumulates into drift), no HIL_SYNC; frames
received by the tick's deadline are handed to the nodes before they advance.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import can

from can_defs.codec import encode
from can_defs.frames import FRAME_LENGTH, HANDSHAKE_TICK, TICK_STEP_MS, FrameId, HilSync
from hil.errors import HilError

#: Wall-clock interval between handshake HIL_SYNC frames (contract: 100 ms).
HANDSHAKE_INTERVAL_S = 0.1
#: Default wait for the ECU's handshake answer: long enough for a cold start of the ECU
#: process (imports, model and paths loaded), also under user-mode Linux.
DEFAULT_HANDSHAKE_TIMEOUT_S = 60.0
#: Default wait for one tick's HIL_SYNC_ACK (an NMPC solve can take a while).
DEFAULT_ACK_TIMEOUT_S = 10.0
# How often a blocked receive wakes up to check that the ECU is still alive.
_POLL_S = 0.25


class TimeMasterError(HilError):
    """The time master could not run the loop."""


class HandshakeTimeoutError(TimeMasterError):
    """The ECU never answered the lockstep start-up handshake."""


class AckTimeoutError(TimeMasterError):
    """The ECU did not acknowledge a tick in time."""


class PeerDiedError(TimeMasterError):
    """The ECU (thread or process) stopped while the master waited for it."""


class HilNode(Protocol):
    """What a time master drives: the plant, the planner, frame monitors."""

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        """Frames this node sends at virtual time ``tick_ms`` (ms)."""

    def receive(self, message: can.Message, tick_ms: int) -> None:
        """A frame received during tick ``tick_ms``."""

    def advance(self, tick_ms: int, dt_s: float) -> None:
        """Move the node's state from ``tick_ms`` to ``tick_ms + dt_s``."""


def _sync_message(tick: int) -> can.Message:
    return can.Message(arbitration_id=int(FrameId.HIL_SYNC), data=encode(HilSync(tick)),
                       is_extended_id=False)


def _ack_tick(message: can.Message) -> int | None:
    """TICK of a well-formed HIL_SYNC_ACK, None for any other frame."""
    if (message.arbitration_id != FrameId.HIL_SYNC_ACK or message.is_extended_id
            or len(message.data) != FRAME_LENGTH):
        return None
    return int.from_bytes(bytes(message.data[0:4]), "little")


@dataclass
class MasterStats:
    """What a master run did: ticks run, frames sent and received (every frame, ACKs
    included; ``stray_acks`` those that answered no pending tick), and for real time the
    ticks whose work finished after their deadline and the worst lateness (s)."""

    ticks: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    stray_acks: int = 0
    overruns: int = 0
    max_lateness_s: float = 0.0


#: Send hook: (tick ms, the nodes' frames due at that tick) -> the frames that reach the
#: bus instead (fault injection, hil/faults.py).
SendHook = Callable[[int, list[can.Message]], list[can.Message]]


class _MasterBase:
    def __init__(self, bus: can.BusABC, nodes: Sequence[HilNode],
                 clock: Callable[[], float], send_hook: SendHook | None = None) -> None:
        self.bus = bus
        self.nodes = list(nodes)
        self.clock = clock
        self.send_hook = send_hook
        self.stats = MasterStats()

    def _send(self, message: can.Message) -> None:
        try:
            self.bus.send(message)
        except can.CanError as e:
            raise TimeMasterError(f"cannot send 0x{message.arbitration_id:03X} on the bus: "
                                  f"{e}") from e
        self.stats.frames_sent += 1

    def _send_due(self, tick_ms: int) -> None:
        frames = [message for node in self.nodes for message in node.frames_due(tick_ms)]
        if self.send_hook is not None:
            # Called every tick, also without frames: held (delayed) frames may be due.
            frames = self.send_hook(tick_ms, frames)
        for message in frames:
            self._send(message)

    def _dispatch(self, message: can.Message, tick_ms: int) -> None:
        self.stats.frames_received += 1
        for node in self.nodes:
            node.receive(message, tick_ms)

    def _advance(self, tick_ms: int) -> None:
        for node in self.nodes:
            node.advance(tick_ms, TICK_STEP_MS / 1000.0)
        self.stats.ticks += 1


class LockstepMaster(_MasterBase):
    """Owner of virtual time in lockstep mode (see the module docstring).

    Args:
        bus: the master's own bus object (it sends the nodes' frames and HIL_SYNC).
        nodes: plant, planner and monitors, in the order their frames are sent.
        handshake_timeout_s: wall-clock limit for the ECU's handshake answer.
        ack_timeout_s: wall-clock limit for each tick's HIL_SYNC_ACK.
        peer_alive: returns None while the ECU runs, else why it stopped (checked while
            waiting, so a crashed ECU is reported at once, not after the timeout).
        clock: monotonic wall clock (s), injectable for tests.
        send_hook: every tick's node frames pass through it before the bus (faults).
    """

    def __init__(self, bus: can.BusABC, nodes: Sequence[HilNode], *,
                 handshake_timeout_s: float = DEFAULT_HANDSHAKE_TIMEOUT_S,
                 ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
                 peer_alive: Callable[[], str | None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 send_hook: SendHook | None = None) -> None:
        super().__init__(bus, nodes, clock, send_hook)
        self.handshake_timeout_s = handshake_timeout_s
        self.ack_timeout_s = ack_timeout_s
        self.peer_alive = peer_alive or (lambda: None)

    def handshake(self) -> float:
        """Run the start-up handshake; returns the wall-clock seconds it took.

        Raises:
            HandshakeTimeoutError: no HIL_SYNC_ACK 0xFFFFFFFF within the timeout.
            PeerDiedError: the ECU stopped meanwhile.
        """
        start = self.clock()
        give_up = start + self.handshake_timeout_s
        while True:
            self._send(_sync_message(HANDSHAKE_TICK))
            next_sync = self.clock() + HANDSHAKE_INTERVAL_S
            while (remaining := next_sync - self.clock()) > 0:
                message = self.bus.recv(timeout=remaining)
                if message is None:
                    continue
                self.stats.frames_received += 1
                if _ack_tick(message) == HANDSHAKE_TICK:
                    return self.clock() - start
            self._check_peer("during the start-up handshake")
            if self.clock() >= give_up:
                raise HandshakeTimeoutError(
                    f"the ECU did not answer the HIL_SYNC handshake (TICK=0xFFFFFFFF) within "
                    f"{self.handshake_timeout_s:.0f} s: is it running in lockstep mode on this "
                    "bus and channel?")

    def tick(self, tick_ms: int) -> None:
        """Run one tick: frames due, HIL_SYNC, wait for its ACK, advance the nodes.

        Raises:
            AckTimeoutError: no HIL_SYNC_ACK with this TICK within ``ack_timeout_s``.
            PeerDiedError: the ECU stopped meanwhile.
        """
        self._send_due(tick_ms)
        self._send(_sync_message(tick_ms))
        give_up = self.clock() + self.ack_timeout_s
        while True:
            remaining = give_up - self.clock()
            if remaining <= 0:
                raise AckTimeoutError(
                    f"no HIL_SYNC_ACK for TICK={tick_ms} ms within {self.ack_timeout_s:g} s "
                    "of wall clock")
            message = self.bus.recv(timeout=min(remaining, _POLL_S))
            if message is None:
                self._check_peer(f"while waiting for the ACK of TICK={tick_ms} ms")
                continue
            acked = _ack_tick(message)
            if acked is None:
                self._dispatch(message, tick_ms)
                continue
            self.stats.frames_received += 1
            if acked == tick_ms:
                break
            # Late answers to repeated handshake frames, or a repeated ACK: the
            # contract's ECU may answer every handshake it saw; nothing to do.
            self.stats.stray_acks += 1
        self._advance(tick_ms)

    def run(self, duration_s: float,
            on_tick: Callable[[int], None] | None = None) -> MasterStats:
        """Handshake, then ticks 0, 5, ... up to (excluding) ``duration_s``."""
        self.handshake()
        for tick_ms in range(0, _duration_ms(duration_s), TICK_STEP_MS):
            self.tick(tick_ms)
            if on_tick is not None:
                on_tick(tick_ms)
        return self.stats

    def _check_peer(self, when: str) -> None:
        reason = self.peer_alive()
        if reason is not None:
            raise PeerDiedError(f"the ECU stopped {when}: {reason}")


class RealTimeMaster(_MasterBase):
    """The same nodes on the wall clock: one tick every 5 ms on absolute deadlines.

    Args:
        bus: the HIL's own bus object.
        nodes: plant, planner and monitors.
        clock: monotonic clock (s), injectable for tests; the waiting itself is a
            blocking receive with a timeout, so a frame is handled as soon as it arrives.
        send_hook: every tick's node frames pass through it before the bus (faults).
    """

    def __init__(self, bus: can.BusABC, nodes: Sequence[HilNode], *,
                 clock: Callable[[], float] = time.monotonic,
                 send_hook: SendHook | None = None) -> None:
        super().__init__(bus, nodes, clock, send_hook)

    def run(self, duration_s: float,
            on_tick: Callable[[int], None] | None = None) -> MasterStats:
        """Ticks 0, 5, ... up to (excluding) ``duration_s`` of wall clock."""
        period_s = TICK_STEP_MS / 1000.0
        deadline = self.clock()
        for tick_ms in range(0, _duration_ms(duration_s), TICK_STEP_MS):
            self._send_due(tick_ms)
            # Frames that arrived up to now count before the plant integrates t -> t + 5.
            while (message := self.bus.recv(timeout=0.0)) is not None:
                self._dispatch(message, tick_ms)
            self._advance(tick_ms)
            deadline += period_s
            lateness = self.clock() - deadline
            if lateness > 0:
                self.stats.overruns += 1
                self.stats.max_lateness_s = max(self.stats.max_lateness_s, lateness)
            # Wait for the next deadline receiving (not sleeping), so a command is latched
            # as soon as the next tick starts.
            while (remaining := deadline - self.clock()) > 0:
                message = self.bus.recv(timeout=remaining)
                if message is not None:
                    self._dispatch(message, tick_ms)
            if on_tick is not None:
                on_tick(tick_ms)
        return self.stats


def _duration_ms(duration_s: float) -> int:
    if not duration_s > 0:
        raise TimeMasterError(f"duration must be > 0 s, got {duration_s!r}")
    return int(round(duration_s * 1000.0))

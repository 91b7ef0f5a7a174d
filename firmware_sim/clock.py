"""Time bases of the ECU: the lockstep TICK clock and the real-time release schedule.

Both give task instants as integer nanoseconds so that comparisons against the contract's
thresholds (20 ms, 100 ms) are exact; lockstep times are multiples of 1 ms.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Callable

from can_defs.frames import HANDSHAKE_TICK

from firmware_sim.config import NS_PER_MS, NS_PER_S, PHASE_FOLLOW_DIVISOR

__all__ = ["HANDSHAKE_TICK", "LockstepClock", "RealtimeSchedule", "SampleRelease", "TickAdvance",
           "TickKind", "clock_ns"]

MonotonicClock = Callable[[], float]


def clock_ns(clock: MonotonicClock) -> int:
    """Read a seconds clock as integer nanoseconds."""
    return int(round(clock() * NS_PER_S))


class TickKind(enum.Enum):
    """How the ECU answers one HIL_SYNC."""

    HANDSHAKE = "handshake"      # reset to before tick 0, ACK 0xFFFFFFFF
    NEW = "new"                  # run the due tasks, then ACK
    REPEATED = "repeated"        # ACK again, run nothing
    NOT_SYNCHRONISED = "not synchronised"  # no handshake yet: ignored, no ACK
    BACKWARDS = "backwards"      # older than the last tick: discarded, no ACK
    JUMP = "jump"                # > 100 ms ahead (rev. 2): adopted, skipped tasks not run


@dataclass(frozen=True)
class TickAdvance:
    """Result of one HIL_SYNC: the kind and the control task instants due, in ms."""

    kind: TickKind
    due_ms: tuple[int, ...] = ()
    skipped: int = 0


#: A TICK more than this ahead of the last one acknowledged is a jump of virtual time
#: (contract, rev. 2); after the handshake the last acknowledged TICK counts as -5.
JUMP_THRESHOLD_MS = 100
#: What the last acknowledged TICK counts as right after the handshake (contract, rev. 2).
BEFORE_TICK_0_MS = -5


class LockstepClock:
    """Virtual time from HIL_SYNC: every task of period P due in (previous TICK, TICK].

    Before the handshake the clock is not synchronised; the handshake puts it "before
    tick 0" (the last TICK counts as -5) so that the first TICK (normally 0) runs the task
    instants from 0 on. A TICK more than ``jump_ms`` ahead is a jump of virtual time
    (contract, rev. 2): it is adopted as the clock, and only a task due at that TICK
    itself is run, never the skipped ones in between.
    """

    def __init__(self, task_period_ms: int, max_catch_up_tasks: int | None = None,
                 jump_ms: int = JUMP_THRESHOLD_MS) -> None:
        self._period_ms = task_period_ms
        self._jump_ms = jump_ms
        # Bound on the tasks of one TICK; with jumps detected at most
        # jump_ms / period + 1 remain, so the argument is kept only for old callers.
        self._max_catch_up = max_catch_up_tasks or (jump_ms // task_period_ms + 1)
        self.synchronised = False
        self.last_tick_ms: int | None = None

    def handshake(self) -> TickAdvance:
        """Reset to "before tick 0"."""
        self.synchronised = True
        self.last_tick_ms = None
        return TickAdvance(TickKind.HANDSHAKE)

    def advance(self, tick_ms: int) -> TickAdvance:
        """Move virtual time to ``tick_ms`` and list the control task instants now due.

        A TICK more than ``jump_ms`` ahead of the last one (``JUMP``) lists only the task
        due at that TICK (if any) and counts the instants in between in ``skipped``.
        """
        if tick_ms == HANDSHAKE_TICK:
            return self.handshake()
        if not self.synchronised:
            return TickAdvance(TickKind.NOT_SYNCHRONISED)
        previous = self.last_tick_ms
        if previous is not None and tick_ms == previous:
            return TickAdvance(TickKind.REPEATED)
        if previous is not None and tick_ms < previous:
            return TickAdvance(TickKind.BACKWARDS)
        after = BEFORE_TICK_0_MS if previous is None else previous
        first = (after // self._period_ms + 1) * self._period_ms
        if tick_ms - after > self._jump_ms:
            instants = (tick_ms - first) // self._period_ms + 1
            due_now = (tick_ms,) if tick_ms % self._period_ms == 0 else ()
            self.last_tick_ms = tick_ms
            return TickAdvance(TickKind.JUMP, due_now, instants - len(due_now))
        count = 0 if first > tick_ms else (tick_ms - first) // self._period_ms + 1
        skipped = max(0, count - self._max_catch_up)
        first += skipped * self._period_ms
        due = tuple(range(first, tick_ms + 1, self._period_ms))
        self.last_tick_ms = tick_ms
        return TickAdvance(TickKind.NEW, due, skipped)

    @staticmethod
    def to_ns(tick_ms: int) -> int:
        """Virtual time in ns."""
        return tick_ms * NS_PER_MS


class RealtimeSchedule:
    """Absolute release times ``next += period`` on a monotonic clock (no drift).

    When the loop falls behind by whole periods the missed releases are skipped (no burst
    of catch-up tasks) and reported, so the caller can count them as overruns.
    """

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.next_release_ns: int | None = None

    def start(self, now_ns: int) -> None:
        """First release at ``now_ns``."""
        self.next_release_ns = now_ns

    def due(self, now_ns: int) -> bool:
        """Whether the next release has come."""
        return self.next_release_ns is not None and now_ns >= self.next_release_ns

    def release(self, now_ns: int) -> tuple[int, int]:
        """Consume the due release: returns (ideal release ns, releases skipped)."""
        assert self.next_release_ns is not None, "start() first"
        ideal = self.next_release_ns
        self.next_release_ns = ideal + self.period_ns
        skipped = 0
        if now_ns >= self.next_release_ns:
            skipped = (now_ns - self.next_release_ns) // self.period_ns + 1
            self.next_release_ns += skipped * self.period_ns
        return ideal, skipped

    def seconds_until_next(self, now_ns: int) -> float:
        """Time to wait before the next release (0 when due), s."""
        if self.next_release_ns is None:
            return 0.0
        return max(0, self.next_release_ns - now_ns) / NS_PER_S


class SampleRelease:
    """Revision 3 release of the control task by the plant's samples (``docs/can-contract.md``,
    "Revision 3"), on integer ns of either time base (TICK in lockstep, monotonic in real time).

    Unanchored (from the start, after `reset`), the caller releases the task on its 25 ms
    clock as in revision 2 and reports each release with `note_release`. A good sample set
    anchors the grid of control instants N_k = anchor + k * period there: the first one,
    and the first after none for more than ``lost_ns`` (the contract's 100 ms); when the
    task ran less than ``min_spacing_ns`` before it, that release stands for the instant
    and the sample does not run the task again; the grid anchors near that release, in phase
    with the samples (`_in_phase`), except for a *paced* plant (25 ms, one sample per period), whose grid anchors at the sample and
    follows each of its samples: one that comes outside the pending instant's window anchors
    it again, one that releases the task moves the instant to its arrival. Anchored,
    instant N is released by the first good sample set arriving in its window
    [N - ``early_ns``, N + ``watchdog_ns``), and by the period watchdog at N + ``watchdog_ns``
    when none came. One release per instant: later samples of the window only refresh the
    newest sample. Two releases are never closer than ``min_spacing_ns``.
    """

    def __init__(self, period_ns: int, early_ns: int, watchdog_ns: int, min_spacing_ns: int,
                 lost_ns: int, sample_period_ns: int) -> None:
        if early_ns < 0 or watchdog_ns <= 0 or early_ns + watchdog_ns + min_spacing_ns > period_ns:
            raise ValueError(f"release window [-{early_ns}, +{watchdog_ns}) ns with a spacing of "
                             f"{min_spacing_ns} ns does not fit the period of {period_ns} ns")
        self.period_ns = period_ns
        self.early_ns = early_ns
        self.watchdog_ns = watchdog_ns
        self.min_spacing_ns = min_spacing_ns
        self.lost_ns = lost_ns
        self.sample_period_ns = sample_period_ns
        #: One sample per control period (a 25 ms plant, slower than a window is wide): its
        #: samples pace the task, and the grid follows each one.
        self.paced = sample_period_ns > early_ns + watchdog_ns
        self.reset()

    def reset(self) -> None:
        """Unanchored, nothing released (start-up, handshake, jump of virtual time)."""
        self.anchored = False
        self.instant_ns = 0              # the pending control instant N (anchored)
        self.instant_released = False
        self.last_release_ns: int | None = None
        self.last_sample_ns: int | None = None

    def note_release(self, now_ns: int) -> None:
        """A release of the caller's own clock (unanchored)."""
        self.last_release_ns = now_ns

    def _release(self, now_ns: int) -> None:
        self.instant_released = True
        self.last_release_ns = now_ns

    def on_time(self, now_ns: int) -> tuple[bool, int]:
        """Close the windows that ended by ``now_ns``: (watchdog release now, instants
        skipped). Of several windows closed unreleased at once (a late loop) only the newest
        is released; the others are skipped (the caller counts them as overruns)."""
        if not self.anchored:
            return False, 0
        missed = 0
        while now_ns >= self.instant_ns + self.watchdog_ns:
            missed += not self.instant_released
            self.instant_ns += self.period_ns
            self.instant_released = False
        if missed:
            self.last_release_ns = now_ns
        return missed > 0, max(0, missed - 1)

    def on_sample(self, arrival_ns: int) -> bool:
        """A good plant sample set arrived at ``arrival_ns`` (call `on_time` first): whether
        it releases the task now."""
        restarted = self.last_sample_ns is None or arrival_ns - self.last_sample_ns > self.lost_ns
        self.last_sample_ns = arrival_ns
        off_window = arrival_ns < self.instant_ns - self.early_ns
        if not self.anchored or restarted or (off_window and self.paced):
            # A paced plant's sample outside the window (a late first sample, a plant whose
            # phase moved) anchors the grid too, or each later one would miss its window.
            return self._anchor(arrival_ns)
        if self.instant_released or off_window:
            return False
        if self.last_release_ns is not None and arrival_ns - self.last_release_ns < self.min_spacing_ns:
            return False
        self._release(arrival_ns)
        if self.paced:
            self.instant_ns = arrival_ns  # the grid follows the plant's phase, drift included
        else:
            self.instant_ns += self._phase_follow(arrival_ns)
        return True

    def _anchor(self, arrival_ns: int) -> bool:
        """Anchor the grid on the sample that arrived at ``arrival_ns``: whether it runs the
        task. Not when the task ran less than the minimum spacing before it: that release
        stands for the instant, and the grid anchors within half a phase step of it, in phase
        with the samples (`_in_phase`; a 10 ms plant: one of its samples is in every window),
        or, for a paced plant, at the sample (so that its next sample comes at its instant)."""
        self.anchored = True
        self.instant_released = True
        if self.last_release_ns is not None and arrival_ns - self.last_release_ns < self.min_spacing_ns:
            self.instant_ns = arrival_ns if self.paced else self._in_phase(self.last_release_ns, arrival_ns)
            return False
        self.instant_ns = arrival_ns
        self.last_release_ns = arrival_ns
        return True

    def _signed_phase_ns(self, offset_ns: int) -> int:
        """((offset + g/2) mod g) - g/2, g = gcd(period, sample period) the samples' phase
        step against the grid (5 ms for a 10 ms plant): the offset's signed phase."""
        step = math.gcd(self.period_ns, self.sample_period_ns)
        return (offset_ns + step // 2) % step - step // 2

    def _phase_follow(self, arrival_ns: int) -> int:
        """The move of the pending instant N for a 10 ms plant's sample that released it at
        ``arrival_ns``: its phase error e = ((arrival - N + g/2) mod g) - g/2 divided by
        ``PHASE_FOLLOW_DIVISOR``, truncated toward zero as C's integer division.

        The first sample in real time can come apart from the phase of the next ones (2 ms
        in a case of ``tests/test_ecu_rev3.py``), and the plant's clock can drift against
        the ECU's: either puts the samples near a window's edge, where jitter gives an instant to the
        watchdog. A fraction of the error per release averages the jitter (1/8: a time
        constant of 8 periods, 0.2 s). In lockstep every sample and instant lie on the 5 ms
        ticks, so e = 0 and nothing moves."""
        error = self._signed_phase_ns(arrival_ns - self.instant_ns)
        move = abs(error) // PHASE_FOLLOW_DIVISOR
        return move if error >= 0 else -move

    def _in_phase(self, release_ns: int, arrival_ns: int) -> int:
        """The instant nearest ``release_ns`` that is in phase with the samples arriving at
        ``arrival_ns`` + k x the sample period, modulo the phase step g = gcd(period, sample
        period) (5 ms for a 10 ms plant): release + ((arrival - release + g/2) mod g) - g/2.
        Samples then sit at the instants and 5 ms after them, 2.5 ms inside both edges of
        their window. Anchored at the release itself (until 2026-12-05), they could sit at
        the window's early edge, where jitter of a few tenths of a millisecond moved every
        other one to the watchdog, 10 ms older."""
        return release_ns + self._signed_phase_ns(arrival_ns - release_ns)

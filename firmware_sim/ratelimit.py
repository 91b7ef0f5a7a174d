"""Log lines that could repeat every cycle, at most one a second per kind, with a count.

A frame that keeps failing, a bus that is gone or a master that keeps sending old TICKs
would otherwise write a line every 5 or 25 ms. `RateLimitedLog.log` writes the first
line of a kind at once and then at most one line a second for that kind, each saying how
many were suppressed since the previous one. The clock is injected (wall clock by default:
the limit is about what a reader of the log sees, also in lockstep).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable

#: Shortest interval between two lines of one kind, s (contract, rev. 2: "at most once a second").
LOG_INTERVAL_S = 1.0


class RateLimitedLog:
    """At most one line per ``interval_s`` per key on ``logger``; suppressed lines are counted."""

    def __init__(self, logger: logging.Logger, interval_s: float = LOG_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._logger = logger
        self._interval_s = interval_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        #: Every call per key, written or not (for tests and diagnostics).
        self.counts: dict[str, int] = {}

    def log(self, key: str, level: int, message: str, *args: object) -> bool:
        """Log ``message % args`` unless a line of ``key`` was written less than the interval
        ago; returns whether it was written."""
        self.counts[key] = self.counts.get(key, 0) + 1
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self._interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        suppressed = self._suppressed.pop(key, 0)
        self._last[key] = now
        if suppressed:
            message += " (%d more like this in the last %.0f s)"
            args = (*args, suppressed, now - last if last is not None else 0.0)
        self._logger.log(level, message, *args)
        return True

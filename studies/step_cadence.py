"""The control step at the ECU's cadence against back to back (part of ``make bench``).

``make bench`` times every controller's steps back to back. The ECU runs one step per
25 ms control period and waits in between, and on a virtual machine that wait is not free:
the host runs other work on the physical core, and the next step starts on caches and
branch predictors that hold someone else's data. This module steps one controller through
the same recorded samples twice, each time freshly built (so both passes do the same
work): back to back, then once per period, sleeping to the next period's start as the ECU's
task waits for its release. The ratio of the two is what a timing run (``make timing``)
adds to the bench's step before any bus or scheduling cost.

Python steps are timed by their wall time around ``step()``; the C core (libecu.so, where it
has the controller) by its own ``ecu_step`` time, as ``make bench``'s C rows.

Usage: through ``python -m studies.bench`` (its "At the control cadence" table); the
functions below for a look at one controller.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from controller.base import CONTROL_PERIOD_S, Controller, VehicleSample
from controller.reference import ReferencePath
from studies.step_timing import BenchError, Percentiles

#: Steps of each pass: 5 s of samples at 25 ms (the first one, set-up, left out).
CADENCE_STEPS = 200


@dataclass(frozen=True)
class CadenceRow:
    """One controller's step back to back and at the cadence, and how it was timed."""

    name: str
    back_to_back: Percentiles
    at_cadence: Percentiles
    clock: str  # "wall around step()" or "ecu_step's own time"

    @property
    def p50_ratio(self) -> float:
        """At the cadence / back to back, p50."""
        return self.at_cadence.p50_ms / self.back_to_back.p50_ms

    @property
    def p99_ratio(self) -> float:
        """At the cadence / back to back, p99."""
        return self.at_cadence.p99_ms / self.back_to_back.p99_ms


def timed_pass(controller: Controller, samples: Sequence[VehicleSample], path: ReferencePath,
               period_s: float | None, own_time: Callable[[Controller], float] | None = None) -> np.ndarray:
    """Step times (s), shape (len(samples) - 1,), the set-up step left out.

    Args:
        controller: freshly built; reset and given ``path`` here.
        period_s: None for back to back; otherwise each step starts at the next multiple of
            ``period_s`` after the first (a sleep in between, as the ECU's task waits).
        own_time: the controller's own time of its last step (s), read after each step;
            None times the wall around ``step()``.
    """
    if len(samples) < 2:
        raise BenchError(f"{len(samples)} samples: at least 2 (the first step is left out)")
    controller.reset()
    controller.set_path(path)
    times = np.empty(len(samples))
    start = time.perf_counter()
    for index, sample in enumerate(samples):
        if period_s is not None:
            pause = start + index * period_s - time.perf_counter()
            if pause > 0.0:
                time.sleep(pause)
        started = time.perf_counter()
        controller.step(sample)
        wall = time.perf_counter() - started
        times[index] = wall if own_time is None else own_time(controller)
    return times[1:]


def cadence_row(name: str, build: Callable[[], Controller], samples: Sequence[VehicleSample],
                path: ReferencePath, clock: str, own_time: Callable[[Controller], float] | None = None,
                period_s: float = CONTROL_PERIOD_S) -> CadenceRow:
    """Both passes of one controller, each on a fresh ``build()``."""
    back_to_back = timed_pass(build(), samples, path, None, own_time)
    at_cadence = timed_pass(build(), samples, path, period_s, own_time)
    return CadenceRow(name, Percentiles.of(back_to_back), Percentiles.of(at_cadence), clock)


def cadence_rows(name: str, samples: Sequence[VehicleSample], path: ReferencePath,
                 period_s: float = CONTROL_PERIOD_S, with_c: bool = True) -> tuple[list[CadenceRow], str | None]:
    """The Python controller ``name`` and, with ``with_c``, its C core (where libecu.so has
    it): the rows, and a note when the C core could not be timed."""
    import firmware_sim.native as native
    from controller.registry import create_controller
    from firmware_sim.errors import EcuError

    rows = [cadence_row(name, lambda: create_controller(name), samples, path, "wall around step()",
                        period_s=period_s)]
    if not with_c or name not in native.NATIVE_CONTROLLERS:
        return rows, None
    if not native.DEFAULT_LIBRARY.is_file() and not os.environ.get("ECU_LIB"):
        return rows, f"C core: not timed at the cadence, {native.DEFAULT_LIBRARY.name} is not built (make firmware)"
    try:
        rows.append(cadence_row(f"{name} (C)", lambda: native.NativeController(name), samples, path,
                                "ecu_step's own time", lambda c: c.last_step_time_s, period_s))
    except EcuError as e:
        return rows, f"C core: not timed at the cadence ({e})"
    return rows, None


def cadence_table(rows: Sequence[CadenceRow], period_s: float = CONTROL_PERIOD_S) -> list[str]:
    """Markdown lines: the table and how to read it."""
    steps = rows[0].back_to_back.n if rows else 0
    lines = [f"At the control cadence ({steps} steps of the same samples, "
             f"each pass on a freshly built controller: back to back, then one step every {period_s * 1e3:g} ms "
             "with a sleep in between, as the ECU's task waits for its release; `studies/step_cadence.py`):", "",
             "| controller | timed by | back to back p50 / p99 (ms) | every period p50 / p99 (ms) | ratio p50 / p99 |",
             "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row.name} | {row.clock} | {row.back_to_back.p50_ms:.3f} / {row.back_to_back.p99_ms:.3f} | "
                     f"{row.at_cadence.p50_ms:.3f} / {row.at_cadence.p99_ms:.3f} | "
                     f"{row.p50_ratio:.2f} / {row.p99_ratio:.2f} |")
    return lines


def cadence_json(rows: Sequence[CadenceRow]) -> list[dict[str, float | str]]:
    """The rows as plain values (ms) for the bench's JSON."""
    return [{"name": r.name, "clock": r.clock, "steps": r.back_to_back.n,
             "back_to_back_p50_ms": r.back_to_back.p50_ms, "back_to_back_p99_ms": r.back_to_back.p99_ms,
             "at_cadence_p50_ms": r.at_cadence.p50_ms, "at_cadence_p99_ms": r.at_cadence.p99_ms,
             "p50_ratio": r.p50_ratio, "p99_ratio": r.p99_ratio} for r in rows]

"""studies/step_cadence.py: both passes step a fresh controller through the same samples,
the second one step per period. Timing figures are not asserted (they depend on the
machine): what is asserted is the work done and the pacing."""
from __future__ import annotations

import time

import pytest

from controller.base import Command, SolverStatus, StepDebug, VehicleSample
from controller.reference import ReferencePath
from studies.step_cadence import cadence_row, cadence_table, timed_pass
from studies.step_timing import BenchError

SAMPLES = [VehicleSample(10.0, 0.0, 0.0, float(k), 0.0, 0.0, 0.0, 0.0, 10.0) for k in range(6)]


class _Counting:
    """A stand-in controller: counts its calls, reports an own step time of 1 ms."""

    name = "counting"

    def __init__(self) -> None:
        self.steps: list[float] = []
        self.resets = 0
        self.last_step_time_s = 0.001

    def reset(self) -> None:
        self.resets += 1

    def set_path(self, path: ReferencePath) -> None:
        self.path = path

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        self.steps.append(time.perf_counter())
        return Command(0.0, 0.0), StepDebug(SolverStatus.SOLVED)


def test_a_paced_pass_starts_one_step_per_period_and_leaves_out_the_first() -> None:
    controller = _Counting()
    times = timed_pass(controller, SAMPLES, ReferencePath.double_lane_change(), 0.01)
    assert times.shape == (len(SAMPLES) - 1,) and controller.resets == 1
    # step k never starts before its instant k x 10 ms after the first; a late start (a busy
    # machine) only shortens the wait before the next one, so the gaps are not bounded below
    offsets = [t - controller.steps[0] for t in controller.steps]
    assert all(offset >= k * 0.01 - 0.001 for k, offset in enumerate(offsets)), offsets
    assert offsets[-1] >= 0.049


def test_own_time_and_both_passes_on_fresh_controllers() -> None:
    built: list[_Counting] = []

    def build() -> _Counting:
        built.append(_Counting())
        return built[-1]

    row = cadence_row("counting", build, SAMPLES, ReferencePath.double_lane_change(), "own",
                      own_time=lambda c: c.last_step_time_s, period_s=0.002)
    assert len(built) == 2 and all(len(c.steps) == len(SAMPLES) for c in built)
    assert row.back_to_back.p50_ms == row.at_cadence.p50_ms == pytest.approx(1.0)  # the own time, read
    assert row.p50_ratio == pytest.approx(1.0) and row.back_to_back.n == len(SAMPLES) - 1
    table = cadence_table([row], period_s=0.002)
    assert "| counting | own | 1.000 / 1.000 | 1.000 / 1.000 | 1.00 / 1.00 |" in table
    assert "one step every 2 ms" in table[0]


def test_too_few_samples_are_refused() -> None:
    with pytest.raises(BenchError, match="at least 2"):
        timed_pass(_Counting(), SAMPLES[:1], ReferencePath.double_lane_change(), None)

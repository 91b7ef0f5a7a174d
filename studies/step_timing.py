"""Controllers timed step by step on the same recorded samples: the measurement that
``make bench`` (``studies/bench.py``) and ``make bench-native`` (``studies/bench_native.py``)
share.

`record_samples` records the samples ``RECORDING_DRIVER`` sees driving the four-wheel plant
through ``RECORDING_SCENARIO`` (`studies.closed_loop.run_closed_loop`); `time_controllers`
feeds them to several controllers side by side, open loop, the order rotated by one per
sample, and summarises each controller's steps as a `ControllerTiming` (the first step,
the one-off set-up, left out). The callers set ``OPENBLAS_NUM_THREADS=1`` before numpy
loads (see ``studies/bench.py``).
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from controller.base import Command, Controller, SolverStatus, StepDebug, VehicleSample
from controller.reference import ReferencePath
from studies.closed_loop import CONTROL_PERIOD_MS

#: The lane change whose samples every controller is fed, and the controller that drives it.
RECORDING_SCENARIO = "dlc_high_mu"
RECORDING_DRIVER = "lmpc"


class BenchError(Exception):
    """The benchmark cannot run (the recording run failed, too few samples)."""


@dataclass(frozen=True)
class Percentiles:
    """p50 / p99 / max of a series of times (ms) and its count."""

    p50_ms: float
    p99_ms: float
    max_ms: float
    n: int

    @classmethod
    def of(cls, times_s: np.ndarray) -> "Percentiles":
        """From times in seconds, shape (n,), n >= 1."""
        ms = np.asarray(times_s, dtype=float) * 1e3
        if ms.ndim != 1 or ms.size == 0:
            raise BenchError(f"no times to summarise (shape {ms.shape})")
        return cls(float(np.percentile(ms, 50)), float(np.percentile(ms, 99)), float(ms.max()),
                   int(ms.size))


@dataclass(frozen=True)
class ControllerTiming:
    """One controller's steps over the recorded samples (the set-up step left out).

    ``solver_share`` is the solver's own time over the step's wall time, both summed over
    the steps; ``not_solved`` counts steps whose status was not SOLVED; ``fallbacks``
    steps that sent the fallback command.
    """

    name: str
    wall: Percentiles
    cpu: Percentiles
    solver: Percentiles
    solver_share: float
    iterations_p50: float
    iterations_max: int
    not_solved: int
    fallbacks: int


class _RecordingController(Controller):
    """Passes every call to ``inner`` and keeps each sample handed to ``step``."""

    def __init__(self, inner: Controller) -> None:
        self.inner = inner
        self.name = inner.name
        self.samples: list[VehicleSample] = []

    def set_path(self, path: ReferencePath) -> None:
        self.inner.set_path(path)

    def reset(self) -> None:
        self.samples.clear()
        self.inner.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        self.samples.append(sample)
        return self.inner.step(sample)


def record_samples(steps: int | None = None, scenario_name: str = RECORDING_SCENARIO,
                   driver: str = RECORDING_DRIVER) -> tuple[list[VehicleSample], ReferencePath, str]:
    """The samples ``driver`` sees while driving the plant through ``scenario_name``.

    Args:
        steps: record only the first ``steps`` control steps (the whole scenario if None).

    Returns:
        The samples, the scenario's reference path and a one-line description.
    """
    from controller.registry import create_controller
    from studies.closed_loop import load_reference_path, run_closed_loop
    from hil.scenario import load_scenario

    scenario = load_scenario(scenario_name)
    if steps is not None:
        if steps < 2:
            raise BenchError(f"--steps {steps}: at least 2 (the first step is left out)")
        scenario = dataclasses.replace(
            scenario, duration_s=min(scenario.duration_s, steps * CONTROL_PERIOD_MS / 1000.0))
    path = load_reference_path(scenario)
    recorder = _RecordingController(create_controller(driver))
    result = run_closed_loop(scenario, recorder, reference_path=path)
    if not result.completed:
        raise BenchError(f"recording run of {driver} on {scenario_name} failed: {result.failure}")
    description = (f"{len(recorder.samples)} samples of `{scenario_name}` ({scenario.description}) "
                   f"as {driver} saw them driving the four-wheel plant")
    return list(recorder.samples), path, description


def time_controllers(controllers: Mapping[str, Controller], samples: Sequence[VehicleSample],
                     path: ReferencePath) -> dict[str, ControllerTiming]:
    """Every controller of ``controllers`` (name -> built controller) fed ``samples`` side
    by side (see the module docstring)."""
    if len(samples) < 2:
        raise BenchError(f"{len(samples)} samples: at least 2 (the first step is left out)")
    if not controllers:
        raise BenchError("no controller to time (none could be built)")
    for controller in controllers.values():
        controller.reset()
        controller.set_path(path)
    names = list(controllers)
    n, order = len(samples), list(names)
    wall = {name: np.empty(n) for name in names}
    cpu = {name: np.empty(n) for name in names}
    debugs: dict[str, list[StepDebug]] = {name: [] for name in names}
    for k, sample in enumerate(samples):
        shift = k % len(order)
        for name in order[shift:] + order[:shift]:
            controller = controllers[name]
            started, started_cpu = time.perf_counter(), time.thread_time()
            _, debug = controller.step(sample)
            wall[name][k] = time.perf_counter() - started
            cpu[name][k] = time.thread_time() - started_cpu
            debugs[name].append(debug)
    timings = {}
    for name in names:
        steps = debugs[name][1:]
        solve = np.array([d.solve_time_s for d in steps])
        iterations = np.array([d.iterations for d in steps])
        timings[name] = ControllerTiming(
            name=name, wall=Percentiles.of(wall[name][1:]), cpu=Percentiles.of(cpu[name][1:]),
            solver=Percentiles.of(solve), solver_share=float(solve.sum() / wall[name][1:].sum()),
            iterations_p50=float(np.median(iterations)), iterations_max=int(iterations.max()),
            not_solved=sum(d.status != SolverStatus.SOLVED for d in steps),
            fallbacks=sum(bool(d.fallback) for d in steps))
    return timings

"""``make bench-native``: the C control core's step against the Python controller's step.

    python -m studies.bench_native [--steps N] [--controllers eso-dkmpc,dkmpc,lmpc]

The samples are those of ``make bench`` (``studies.bench.record_samples``: LMPC driving
the four-wheel plant through the high-mu double lane change). For each controller the
Python controller and the C core (``firmware_sim.native.NativeController``, libecu.so)
are fed the same samples alternately in one process (``studies.bench.time_controllers``:
open loop, the order rotated per sample, the first step left out). Two C figures: the
step as the C core times itself (``ecu_step`` alone: what an ECU would spend) and the
wall time of the Python call into it (ctypes and the result's conversion added).
The commands of both are compared as well: the largest difference is printed.

The last line is one JSON object: ``c_p50_us``, ``c_p99_us`` (the C core's own step
time of ESO-DKMPC), ``python_p50_us``, ``python_p99_us`` (the Python step's wall time)
and, per controller, every figure. Figures depend on the machine and its load.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402 (after the BLAS setting on purpose)
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Sequence  # noqa: E402

import numpy as np  # noqa: E402

from controller.base import Command, Controller, StepDebug, VehicleSample  # noqa: E402
from controller.reference import ReferencePath  # noqa: E402
from firmware_sim.errors import EcuError  # noqa: E402
from firmware_sim.native import NATIVE_CONTROLLERS, NativeController  # noqa: E402
from studies.bench import BenchError, record_samples, time_controllers  # noqa: E402
from studies.machine import load_average, machine_description  # noqa: E402

#: The controller of the JSON line's four headline figures.
HEADLINE = "eso-dkmpc"
#: Issue 18's target for the C step's p99 (us).
TARGET_P99_US = 100.0


class _Recorded(Controller):
    """Passes every call to ``inner``; keeps each step's command and, for the C core, its
    own step time (s)."""

    def __init__(self, inner: Controller) -> None:
        self.inner, self.name = inner, inner.name
        self.commands: list[Command] = []
        self.step_times_s: list[float] = []

    def set_path(self, path: ReferencePath) -> None:
        self.inner.set_path(path)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        command, debug = self.inner.step(sample)
        self.commands.append(command)
        self.step_times_s.append(getattr(self.inner, "last_step_time_s", float("nan")))
        return command, debug


def bench_one(name: str, samples: Sequence[VehicleSample], path: ReferencePath) -> dict[str, float]:
    """Python and C steps of controller ``name`` on ``samples``, figures in us."""
    from controller.registry import create_controller

    python = _Recorded(create_controller(name))
    native = _Recorded(NativeController(name))
    timings = time_controllers({"python": python, "c": native}, samples, path)
    own = np.array(native.step_times_s[1:]) * 1e6
    steer_difference = max(abs(a.steer_angle - b.steer_angle) for a, b in zip(python.commands, native.commands))
    return {"c_p50_us": float(np.percentile(own, 50)), "c_p99_us": float(np.percentile(own, 99)),
            "c_max_us": float(own.max()),
            "c_call_p50_us": timings["c"].wall.p50_ms * 1e3, "c_call_p99_us": timings["c"].wall.p99_ms * 1e3,
            "c_solver_p50_us": timings["c"].solver.p50_ms * 1e3,
            "c_call_cpu_p50_us": timings["c"].cpu.p50_ms * 1e3, "c_call_cpu_p99_us": timings["c"].cpu.p99_ms * 1e3,
            "python_p50_us": timings["python"].wall.p50_ms * 1e3,
            "python_p99_us": timings["python"].wall.p99_ms * 1e3,
            "python_cpu_p50_us": timings["python"].cpu.p50_ms * 1e3,
            "python_cpu_p99_us": timings["python"].cpu.p99_ms * 1e3,
            "python_solver_p50_us": timings["python"].solver.p50_ms * 1e3,
            "iterations_p50": timings["c"].iterations_p50, "steps": timings["c"].wall.n,
            "max_steer_difference_rad": steer_difference}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=None, help="only the first N control steps")
    parser.add_argument("--controllers", default=",".join(NATIVE_CONTROLLERS),
                        help=f"comma-separated, of {', '.join(NATIVE_CONTROLLERS)}")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    unknown = [n for n in names if n not in NATIVE_CONTROLLERS]
    if unknown or not names:
        print(f"error: --controllers: {', '.join(unknown) or '(none)'} not in the C core "
              f"({', '.join(NATIVE_CONTROLLERS)})", file=sys.stderr)
        return 2
    try:
        load_start = load_average()
        samples, path, description = record_samples(args.steps)
        results = {name: bench_one(name, samples, path) for name in names}
    except (BenchError, EcuError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{description}; {machine_description()}; load average {load_start[0]:.2f} at the start, "
          f"{load_average()[0]:.2f} at the end")
    print(f"{'controller':<10} {'C p50':>7} {'C p99':>7} {'C max':>7} {'call p99':>8} {'cpu p99':>8} "
          f"{'Py p50':>7} {'Py p99':>7} {'Py cpu p99':>10}")
    for name, r in results.items():
        print(f"{name:<10} {r['c_p50_us']:7.1f} {r['c_p99_us']:7.1f} {r['c_max_us']:7.1f} {r['c_call_p99_us']:8.1f} "
              f"{r['c_call_cpu_p99_us']:8.1f} {r['python_p50_us']:7.1f} {r['python_p99_us']:7.1f} "
              f"{r['python_cpu_p99_us']:10.1f}  max |steer C - Python| {r['max_steer_difference_rad']:.1e} rad")
    print("(us. C: ecu_step's own wall time; call: the Python call into it through ctypes, wall and "
          "thread CPU time; Py: the Python controller's step, wall and CPU time)")
    head = results.get(HEADLINE) or next(iter(results.values()))
    headline_name = HEADLINE if HEADLINE in results else next(iter(results))
    verdict = "met" if head["c_p99_us"] <= TARGET_P99_US else "NOT met"
    print(f"target: {headline_name} C step p99 <= {TARGET_P99_US:.0f} us: {verdict} ({head['c_p99_us']:.1f} us)")
    summary = {key: head[key] for key in ("c_p50_us", "c_p99_us", "python_p50_us", "python_p99_us")}
    summary.update(controller=headline_name, controllers=results)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Per-step compute time of the controllers on the double lane change (benchmark, not a test).

    python -m studies.controller_timing [--controllers lmpc,dkmpc,...] [--out results/controller_timing.md]

Each controller drives ``models.vehicle.FourWheelVehicle`` (mu 0.85, 35 km/h, the paper's
high-mu case) along ``ReferencePath.double_lane_change()`` for ``--steps`` control steps.
The wall time of ``step()`` is measured here, around the call (the controller itself never
reads a clock); the solver's own time (OSQP ``run_time`` / IPOPT ``t_wall_total``) comes
from ``StepDebug.solve_time_s``. The first step (one-off set-up) is left out. Besides the wall time the table gives the CPU
time of the calling thread (``time.thread_time``), which a busy machine does not inflate:
on a shared 2-core machine the wall figures include time spent waiting for a core.
BLAS runs single-threaded (``OPENBLAS_NUM_THREADS=1``): on a 2-core machine a threaded
BLAS turns a 3x3 matrix exponential from ~25 us into tens of ms whenever the other core is
busy.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402 (after the BLAS setting on purpose)
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from controller.base import VehicleSample  # noqa: E402
from controller.errors import ControllerError  # noqa: E402
from models.errors import ModelError  # noqa: E402
from controller.reference import ReferencePath, lateral_error  # noqa: E402
from controller.registry import CONTROLLER_NAMES, create_controller  # noqa: E402

SPEED_MPS = 35.0 / 3.6
PLANT_SUBSTEPS = 5  # the plant advances in 5 ms ticks, as on the bus


def run_one(name: str, steps: int) -> dict[str, float]:
    """Closed loop of ``steps`` control steps; timing and tracking figures."""
    from models.vehicle import FourWheelVehicle, VehicleCommand
    from models.vehicle_params import load_vehicle_params

    controller = create_controller(name)
    path = ReferencePath.double_lane_change()
    controller.set_path(path)
    plant = FourWheelVehicle(load_vehicle_params(mu=0.85))
    plant.reset(vx=SPEED_MPS)
    wall, cpu, solver, iterations, errors, fallbacks = [], [], [], [], [], 0
    for _ in range(steps):
        out = plant.outputs()
        sample = VehicleSample(out.vx, out.vy, out.yaw_rate, out.x, out.y, out.yaw, out.steer_angle,
                               out.drive_torque, SPEED_MPS)
        started, started_cpu = time.perf_counter(), time.thread_time()
        command, debug = controller.step(sample)
        wall.append(time.perf_counter() - started)
        cpu.append(time.thread_time() - started_cpu)
        solver.append(debug.solve_time_s)
        iterations.append(debug.iterations)
        fallbacks += debug.fallback
        errors.append(abs(lateral_error(path, out.x, out.y).lateral_error))
        for _ in range(PLANT_SUBSTEPS):
            plant.step(VehicleCommand(drive_torque=command.drive_torque, steer_angle=command.steer_angle), 0.005)
    wall_ms, solver_ms, cpu_ms = (np.array(values[1:]) * 1e3 for values in (wall, solver, cpu))
    return {"p50": np.percentile(wall_ms, 50), "p99": np.percentile(wall_ms, 99), "max": wall_ms.max(),
            "cpu_p50": np.percentile(cpu_ms, 50), "cpu_p99": np.percentile(cpu_ms, 99),
            "solver_p50": np.percentile(solver_ms, 50), "solver_p99": np.percentile(solver_ms, 99),
            "iterations_p50": float(np.median(iterations[1:])), "iterations_max": float(max(iterations[1:])),
            "fallbacks": fallbacks, "max_lateral_error": max(errors), "steps": steps - 1}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--controllers", default=",".join(CONTROLLER_NAMES))
    parser.add_argument("--steps", type=int, default=520, help="control steps (520 = 13 s, the whole manoeuvre)")
    parser.add_argument("--out", type=Path, default=None, help="also write a Markdown table here")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    rows = [f"Per-step time on `{platform.node()}` ({platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the start), "
            f"`python -m studies.controller_timing --steps {args.steps}`, "
            "DLC 35 km/h, mu 0.85, FourWheelVehicle.", "",
            "| controller | step wall p50 / p99 / max (ms) | step CPU p50 / p99 (ms) | solver p50 / p99 (ms) "
            "| iterations p50 / max | fallbacks | max abs e_Y (m) |",
            "|---|---|---|---|---|---|---|"]
    for name in names:
        try:
            r = run_one(name, args.steps)
        except (ControllerError, ModelError, OSError, ImportError) as e:
            print(f"error: {name}: {e}", file=sys.stderr)
            return 1
        rows.append(f"| {name} | {r['p50']:.3f} / {r['p99']:.3f} / {r['max']:.3f} | {r['cpu_p50']:.3f} / "
                    f"{r['cpu_p99']:.3f} | {r['solver_p50']:.3f} / {r['solver_p99']:.3f} | "
                    f"{r['iterations_p50']:.0f} / {r['iterations_max']:.0f} | "
                    f"{r['fallbacks']} | {r['max_lateral_error']:.3f} |")
        print(rows[-1], flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(rows) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

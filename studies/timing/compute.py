"""``make bench``: per-step compute time of the four controllers side by side, with the
paper's averages beside them, and where the time of the ESO-DKMPC step and of the ECU's
whole control task goes (cProfile).

    python -m studies.timing.compute [--steps 520] [--profile-steps 300] [--out results/bench.md]

The timing itself is `studies.controller_timing.run_one` (the controller's closed loop on the
four-wheel plant, 35 km/h, mu 0.85, the double lane change; wall and thread-CPU time
measured around ``step()``), run here for the four controllers in one process, one after
the other. The paper (Sec. IV, CasADi / IPOPT on an Intel i7 at 1.10 GHz) reports average
times per step; ours are medians and p99 (`run_one` gives percentiles).

Profiles: cProfile around ``step()`` of ESO-DKMPC in the same closed loop, and around the
ECU's ``_control_task`` during a lockstep HIL run of ESO-DKMPC on the virtual bus
(``hil.session.run_hil``, dlc_high_mu), both sorted by own time.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import io  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

from studies.controller_timing import PLANT_SUBSTEPS, SPEED_MPS, run_one  # noqa: E402
from controller.registry import CONTROLLER_NAMES  # noqa: E402

#: Paper's average computation time per step, ms (CasADi / IPOPT, Intel i7 @ 1.10 GHz).
PAPER_MS = {"lmpc": 2.36, "dkmpc": 261.0, "eso-dkmpc": 370.0, "nmpc": 3076.0}
DISPLAY = {"eso-dkmpc": "ESO-DKMPC", "dkmpc": "DKMPC", "lmpc": "LMPC", "nmpc": "NMPC"}
TOP_FUNCTIONS = 15
#: Cumulative times reported above each profile: (label, file name, function name).
BREAKDOWN = (("Ecu._control_task", "ecu.py", "_control_task"),
             ("controller step()", "mpc_base.py", "step"),
             ("QP data + OSQP", "steering_qp.py", "solve"),
             ("OSQP solve", "~", "<built-in method osqp.ext_builtin.solve>"),
             ("OSQP update", "~", "<built-in method osqp.ext_builtin.update_data_mat>"),
             ("frame encode (can_defs)", "codec.py", "encode"),
             ("bus send", "virtual.py", "send"))


def bench_table(steps: int) -> list[str]:
    """Markdown table of `run_one` for the four controllers, ratios to LMPC, the paper's."""
    results = {name: run_one(name, steps) for name in CONTROLLER_NAMES}
    lmpc = results["lmpc"]
    lines = ["| controller | step wall p50 / p99 / max (ms) | step CPU p50 / p99 (ms) "
             "| solver p50 (ms) | p50 / LMPC p50 | paper avg (ms) | paper / LMPC "
             "| paper avg / our p50 |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(
            f"| {DISPLAY[name]} | {r['p50']:.3f} / {r['p99']:.3f} / {r['max']:.3f} "
            f"| {r['cpu_p50']:.3f} / {r['cpu_p99']:.3f} | {r['solver_p50']:.3f} "
            f"| {r['p50'] / lmpc['p50']:.2f} | {PAPER_MS[name]:g} "
            f"| {PAPER_MS[name] / PAPER_MS['lmpc']:.1f} | {PAPER_MS[name] / r['p50']:.0f}x |")
        print(lines[-1], flush=True)
    return lines


def _top(profile: cProfile.Profile, total_label: str, n: int = TOP_FUNCTIONS) -> list[str]:
    """The ``n`` functions with the most own time, as a Markdown table."""
    stats = pstats.Stats(profile, stream=io.StringIO())
    rows = []
    total = 0.0
    for (file, line, function), (_, ncalls, tottime, cumtime, _) in stats.stats.items():
        total += tottime
        rows.append((tottime, cumtime, ncalls, f"{Path(file).name}:{line}({function})"))
    rows.sort(reverse=True)
    cumulative: dict[tuple[str, str], float] = {}
    for (file, _, function), (_, _, _, cumtime, _) in stats.stats.items():
        key = (Path(file).name, function)
        # nested functions of one name (FrameSender.encode -> encode): the outermost
        cumulative[key] = max(cumulative.get(key, 0.0), cumtime)
    parts = [f"{label} {cumulative[(file, function)] * 1e3:.0f} ms"
             for label, file, function in BREAKDOWN if (file, function) in cumulative]
    lines = [f"{total_label}: {total * 1e3:.0f} ms of own time in all profiled functions; "
             f"cumulative: {', '.join(parts)}.", "",
             "| function | calls | own time (ms) | share | cumulative (ms) |",
             "|---|---|---|---|---|"]
    for tottime, cumtime, ncalls, name in rows[:n]:
        lines.append(f"| `{name}` | {ncalls} | {tottime * 1e3:.1f} | "
                     f"{100 * tottime / total:.1f} % | {cumtime * 1e3:.1f} |")
    return lines


def profile_step(name: str, steps: int) -> list[str]:
    """cProfile around ``step()`` of ``name`` in the closed loop of studies.controller_timing."""
    from controller.base import VehicleSample
    from controller.reference import ReferencePath
    from controller.registry import create_controller
    from models.vehicle import FourWheelVehicle, VehicleCommand
    from models.vehicle_params import load_vehicle_params

    controller = create_controller(name)
    controller.set_path(ReferencePath.double_lane_change())
    plant = FourWheelVehicle(load_vehicle_params(mu=0.85))
    plant.reset(vx=SPEED_MPS)
    profile = cProfile.Profile()
    for index in range(steps):
        out = plant.outputs()
        sample = VehicleSample(out.vx, out.vy, out.yaw_rate, out.x, out.y, out.yaw,
                               out.steer_angle, out.drive_torque, SPEED_MPS)
        if index:  # the first step sets the solver up: left out, as in the benchmark
            profile.enable()
        command, _ = controller.step(sample)
        profile.disable()
        for _ in range(PLANT_SUBSTEPS):
            plant.step(VehicleCommand(command.drive_torque, command.steer_angle), 0.005)
    return _top(profile, f"{DISPLAY[name]} `step()` x {steps - 1}")


def profile_ecu_task(name: str) -> list[str]:
    """cProfile around the ECU's control task in a lockstep HIL run on the virtual bus."""
    from firmware_sim.ecu import Ecu
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    profile = cProfile.Profile()
    original = Ecu._control_task

    def profiled(self: Any, *args: Any, **kwargs: Any) -> None:
        profile.enable()  # per thread: only the ECU thread's task is profiled
        try:
            original(self, *args, **kwargs)
        finally:
            profile.disable()

    Ecu._control_task = profiled  # type: ignore[method-assign]
    try:
        result = run_hil(load_scenario("dlc_high_mu"), default_options(name))
    finally:
        Ecu._control_task = original  # type: ignore[method-assign]
    cycles = len(result.ecu_trace["time"])
    return _top(profile, f"ECU control task with {DISPLAY[name]}, {cycles} cycles "
                         "(lockstep, dlc_high_mu)")


def main(argv: list[str] | None = None) -> int:
    """Benchmark, profiles, Markdown report."""
    parser = argparse.ArgumentParser(prog="python -m studies.timing.compute",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=520, help="control steps per controller")
    parser.add_argument("--profile-steps", type=int, default=300)
    parser.add_argument("--out", type=Path, default=Path("results/bench.md"))
    args = parser.parse_args(argv)
    if args.steps < 2 or args.profile_steps < 2:
        print("error: --steps and --profile-steps must be at least 2", file=sys.stderr)
        return 1
    load = os.getloadavg()[0]
    lines = ["# Controller compute time per step (issue 9, `make bench`)", "",
             f"`python -m studies.timing.compute --steps {args.steps}` on `{platform.node()}` "
             f"({platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load "
             f"average {load:.2f} at the start), one process, BLAS single-threaded. Closed "
             "loop on the four-wheel plant, DLC at 35 km/h, mu 0.85 (`studies.controller_timing.run_one`)"
             "; the first step (set-up) left out. Paper: average per step, CasADi / IPOPT, "
             "Intel i7 @ 1.10 GHz. Ours: OSQP (QP controllers) and CasADi / IPOPT (NMPC).", "",
             *bench_table(args.steps), ""]
    lines += ["## Where the ESO-DKMPC step's time goes", "",
              *profile_step("eso-dkmpc", args.profile_steps), "",
              "## Where the ECU's control task's time goes", "",
              *profile_ecu_task("eso-dkmpc"), "",
              "cProfile adds its own cost per call (Python functions more than numpy's C "
              "code); shares are indicative, the benchmark table gives the real times. The "
              "ECU profile runs on python-can's `virtual` bus, whose `send` deep-copies each "
              "message for every receiver: its bus send cost is not that of a CAN driver.", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

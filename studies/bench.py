"""``make bench``: the one compute-time benchmark of the controllers, side by side.

    python -m studies.bench [--steps N] [--controllers a,b,...] [--no-ecu] [--no-c] [--no-cadence]
        [--profile NAME] [--out results/bench.md] [--json results/bench.json]

1. Recording (``studies/step_timing.py``, shared with ``make bench-native``):
   ``RECORDING_DRIVER`` (LMPC) drives the four-wheel plant through the
   ``RECORDING_SCENARIO`` double lane change (`studies.closed_loop.run_closed_loop`, the
   HIL's timing: 5 ms ticks, plant samples every 10 ms, control every 25 ms); every
   `VehicleSample` handed to the controller is recorded.
2. Timing: every controller the registry builds (``controller.registry.CONTROLLERS``, read
   at run time: the paper's four and any added there join the table) is built, given the same path and fed the same
   recorded samples, in one process. At each sample every controller takes its step in
   turn, the order rotated by one per sample, so a busy moment of a shared machine falls
   on all of them alike. Around each ``step()`` the wall time (``time.perf_counter``) and
   the calling thread's CPU time (``time.thread_time``, which time spent waiting for a core
   does not inflate) are measured; the solver's own time (OSQP ``solve_time`` / IPOPT
   ``t_wall_total``) comes from ``StepDebug.solve_time_s``. Each controller's first step
   (one-off set-up) is left out. Open loop: the commands are not applied, so every
   controller sees exactly the same inputs.
3. The C core (issue 18, ``make firmware``): each controller the C firmware has is fed
   the same samples once more, alternately with its Python twin (one C core per process,
   so one at a time: ``studies.bench_native.c_step_timing``, also ``make bench-native``'s
   measurement); its row "NAME (C)" gives ``ecu_step``'s own wall time inside libecu.so and
   the thread CPU time of the call through ctypes. Left out with ``--no-c``, or with a
   note when libecu.so is not built.
4. ECU overhead: the ECU (`firmware_sim.ecu.Ecu`) with a one-line scripted law, in
   lockstep on a private python-can virtual bus, fed the recorded samples as plant frames:
   its control task time (mode logic, guard, encode and TX of two frames) is what the ECU
   adds to a controller's step.
5. At the control cadence (``studies/step_cadence.py``; ``--no-cadence`` leaves it out):
   ESO-DKMPC (Python, and its C core) on the first ``CADENCE_STEPS`` samples, back to back
   and then one step per 25 ms period with a sleep in between, as the ECU runs it: on a
   virtual machine the wait costs the next step its warm caches.

BLAS runs single-threaded (``OPENBLAS_NUM_THREADS=1``, set before numpy is imported): on a
2-core machine a threaded OpenBLAS turns a 3x3 matrix exponential from microseconds into
milliseconds whenever the other core is busy. Figures depend on the machine and its load;
the header names both. ``--profile NAME`` prints a cProfile of NAME's steps on the same
samples (own time per function) to stdout; it writes nothing.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402 (after the BLAS setting on purpose)
import cProfile  # noqa: E402
import dataclasses  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Mapping, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from controller.base import Controller, VehicleSample  # noqa: E402
from controller.reference import ReferencePath  # noqa: E402
from studies.closed_loop import CONTROL_PERIOD_MS, PLANT_PERIOD_MS, TICK_MS  # noqa: E402
from studies.machine import load_average, machine_description  # noqa: E402
from studies.speed_reference import speed_reference  # noqa: E402
from studies.step_cadence import CADENCE_STEPS, CadenceRow, cadence_json, cadence_rows, cadence_table  # noqa: E402
from studies.step_timing import (BenchError, ControllerTiming, Percentiles, record_samples,  # noqa: E402
                                 time_controllers)

#: The controller every step time is divided by.
BASELINE = "lmpc"
#: Issue 14's goal: ESO-DKMPC's step within this multiple of LMPC's, in the same run.
GOAL_CONTROLLER = "eso-dkmpc"
GOAL_RATIO = 1.5
#: Paper Sec. IV-C: average computation time per step (ms), MATLAB / CasADi / IPOPT on an
#: Intel i7 at 1.10 GHz.
PAPER_MEAN_MS = {"lmpc": 2.36, "dkmpc": 261.0, "eso-dkmpc": 370.0, "nmpc": 3076.0}
#: The label of the ECU overhead's row.
ECU_OVERHEAD_ROW = "ECU overhead (no law)"
TOP_FUNCTIONS = 15
#: The row of NMPC with its NLP compiled (controller/nlp_library.py), as in real time.
NMPC_COMPILED_ROW = "nmpc (compiled NLP)"


def registered_names() -> list[str]:
    """Every controller name the registry builds, in its order, read now (not at import)."""
    from controller import registry

    return list(registry.CONTROLLERS)


def build_controllers(names: Sequence[str]) -> tuple[dict[str, Controller], dict[str, str]]:
    """The controllers of ``names`` that build, and for the others why not (so one
    controller's missing artefact or bad tuning table does not hide the rest)."""
    from controller.registry import create_controller

    built, errors = {}, {}
    for name in names:
        try:
            built[name] = create_controller(name)
        except Exception as e:  # noqa: BLE001 - reported in the table's notes and the exit status
            errors[name] = f"{type(e).__name__}: {e}"
    if "nmpc" in built:  # NMPC as the real-time ECU runs it: the NLP compiled, no budget here
        try:
            compiled = create_controller("nmpc")
            compiled.set_time_budget(None, compiled=True)  # type: ignore[attr-defined]
            built[NMPC_COMPILED_ROW] = compiled
        except Exception as e:  # noqa: BLE001 - as above
            errors[NMPC_COMPILED_ROW] = f"{type(e).__name__}: {e}"
    return built, errors


def measure_ecu_overhead(samples: Sequence[VehicleSample]) -> dict[str, Any]:
    """The ECU's control task time with a one-line law, lockstep, fed ``samples``.

    One control cycle per sample (5 ticks of 5 ms): the sample's plant frames every 10 ms,
    PLANNER_REQ every 25 ms, HIL_SYNC every tick. Returns the control task time (the ECU's
    own timing record) and the wall time per tick (all frames of the tick handled up to
    the HIL_SYNC_ACK), each as :class:`Percentiles` in a dict, and the final mode.
    """
    from firmware_sim.ecu import Ecu
    from hil.bus import BusConfig, open_bus, private_virtual_channel
    from hil.ecu_harness import PeerNodes, ScriptedController, pump

    bus = BusConfig("virtual", private_virtual_channel("bench"))
    ticks_per_cycle = CONTROL_PERIOD_MS // TICK_MS
    with open_bus(bus) as ecu_bus, open_bus(bus) as peer_bus:
        ecu = Ecu(ecu_bus, "scripted", {1: Path("straight")}, lockstep=True,
                  controller_factory=lambda name: ScriptedController(solve_time_s=0.0),
                  path_loader=str)
        peers = PeerNodes(peer_bus)
        peers.send_handshake()
        pump(ecu, ecu_bus)
        tick_times = np.empty(len(samples) * ticks_per_cycle)
        for index in range(tick_times.size):
            t_ms = index * TICK_MS
            if t_ms % PLANT_PERIOD_MS == 0:
                sample = samples[t_ms // CONTROL_PERIOD_MS]
                peers.send_plant(vx=sample.vx, vy=sample.vy, yaw_rate=sample.yaw_rate,
                                 x=sample.x, y=sample.y, yaw=sample.yaw,
                                 steer_angle=sample.steer_angle, drive_torque=sample.drive_torque)
            if t_ms % CONTROL_PERIOD_MS == 0:
                peers.send_planner()
            peers.send_sync(t_ms)
            started = time.perf_counter()
            pump(ecu, ecu_bus)
            tick_times[index] = time.perf_counter() - started
            peers.received()
        ecu.close()
        task = ecu.timing.column("task_time")
        task = task[np.isfinite(task)][1:]  # the first cycle (engagement) left out
        return {"control_task": Percentiles.of(task), "tick": Percentiles.of(tick_times),
                "final_mode": ecu.mode.name}


def _ratio(value: float, baseline: float | None) -> str:
    return f"{value / baseline:.2f}" if baseline else "-"


def bench_table(timings: Mapping[str, ControllerTiming], overhead: Mapping[str, Any] | None) -> list[str]:
    """The Markdown table: one row per controller (the C core's rows "NAME (C)" among them),
    then the ECU overhead's row."""
    base = timings.get(BASELINE)
    lines = ["| controller | step wall p50 / p99 / max (ms) | step CPU p50 / p99 (ms) "
             "| solver p50 / p99 (ms) | solver share | iterations p50 / max | not solved / fallback "
             f"| p50 / {BASELINE} p50 | p99 / {BASELINE} p99 | paper avg (ms) | paper / {BASELINE} |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    paper_base = PAPER_MEAN_MS.get(BASELINE)
    for name, t in timings.items():
        paper = PAPER_MEAN_MS.get(name)
        lines.append(
            f"| {name} | {t.wall.p50_ms:.3f} / {t.wall.p99_ms:.3f} / {t.wall.max_ms:.3f} "
            f"| {t.cpu.p50_ms:.3f} / {t.cpu.p99_ms:.3f} "
            f"| {t.solver.p50_ms:.3f} / {t.solver.p99_ms:.3f} | {100 * t.solver_share:.0f} % "
            f"| {t.iterations_p50:.0f} / {t.iterations_max} | {t.not_solved} / {t.fallbacks} "
            f"| {_ratio(t.wall.p50_ms, base.wall.p50_ms if base else None)} "
            f"| {_ratio(t.wall.p99_ms, base.wall.p99_ms if base else None)} "
            f"| {f'{paper:g}' if paper else '-'} "
            f"| {f'{paper / paper_base:.0f}' if paper and paper_base else '-'} |")
    if overhead is not None:
        task = overhead["control_task"]
        lines.append(f"| {ECU_OVERHEAD_ROW} | {task.p50_ms:.3f} / {task.p99_ms:.3f} / "
                     f"{task.max_ms:.3f} | - | - | - | - | - | - | - | - | - |")
    return lines


def c_core_timings(names: Sequence[str], samples: Sequence[VehicleSample],
                   path: ReferencePath) -> tuple[dict[str, ControllerTiming], str | None]:
    """The C core's rows ("NAME (C)") for the controllers of ``names`` it has, and a note
    when it could not be timed (libecu.so not built, its data file refused)."""
    from firmware_sim.errors import EcuError
    from firmware_sim.native import DEFAULT_LIBRARY, NATIVE_CONTROLLERS
    from studies.bench_native import c_step_timing

    if not DEFAULT_LIBRARY.is_file() and not os.environ.get("ECU_LIB"):
        return {}, f"C core: not timed, {DEFAULT_LIBRARY.name} is not built (make firmware)"
    rows = {}
    try:
        for name in (n for n in names if n in NATIVE_CONTROLLERS):
            _, core, _ = c_step_timing(name, samples, path)
            rows[core.name] = core
    except EcuError as e:
        return rows, f"C core: not timed ({e})"
    return rows, None


def goal_line(timings: Mapping[str, ControllerTiming]) -> str | None:
    """Issue 14's goal read from this run, or None when either controller is missing."""
    goal, base = timings.get(GOAL_CONTROLLER), timings.get(BASELINE)
    if goal is None or base is None:
        return None
    ratio = goal.wall.p50_ms / base.wall.p50_ms
    return (f"Issue 14 goal, {GOAL_CONTROLLER} step within {GOAL_RATIO:g}x {BASELINE}'s in the same "
            f"run: p50 ratio {ratio:.2f} ({'met' if ratio <= GOAL_RATIO else 'NOT met'}); "
            f"p99 ratio {goal.wall.p99_ms / base.wall.p99_ms:.2f}.")


def machine_lines(load_start: tuple[float, float, float], load_end: tuple[float, float, float],
                  speed_ms: float) -> list[str]:
    """Where and under what load the benchmark ran; ``speed_ms`` the speed reference."""
    import osqp

    return [f"- Machine: `{platform.node()}`, {machine_description()}, numpy {np.__version__}, "
            f"OSQP {getattr(osqp, '__version__', '?')}; BLAS threads "
            f"`OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}`.",
            f"- Load average (1 / 5 / 15 min): {' / '.join(f'{v:.2f}' for v in load_start)} at the "
            f"start, {' / '.join(f'{v:.2f}' for v in load_end)} at the end. A load above "
            f"{os.cpu_count()} (the CPUs) means other work was waiting for a core: the wall "
            "tails then include that waiting, the CPU-time columns do not.",
            f"- Speed reference: {speed_ms:.2f} ms (a fixed workload of a Python loop and "
            "small numpy operations, the fastest of 7 runs, `studies/speed_reference.py`): a virtual "
            "machine's CPU name does not say how fast its host is. Compare step times between "
            "results files only where this figure is alike."]


def report(timings: Mapping[str, ControllerTiming], overhead: Mapping[str, Any] | None,
           recording: str, command: str, load_start: tuple[float, float, float],
           load_end: tuple[float, float, float], not_built: Mapping[str, str] | None = None,
           c_rows: Mapping[str, ControllerTiming] | None = None, c_note: str | None = None,
           speed_ms: float = float("nan"), cadence: Sequence[CadenceRow] = (),
           cadence_note: str | None = None) -> str:
    """The whole Markdown file: header, the table, how to read it (and the controllers
    that could not be built, with why; the C core's rows ``c_rows`` or why there are none;
    ``speed_ms`` the speed reference measured at the start; ``cadence``: the headline
    controller's step at the control cadence, ``studies.step_cadence``)."""
    lines = ["# Controller compute time per step (`make bench`)", "",
             f"`{command}`, one process, one run.", "",
             *machine_lines(load_start, load_end, speed_ms),
             f"- Inputs: {recording}; every controller fed the same samples in turn (order "
             "rotated per sample), open loop; each controller's first step (set-up) left out.",
             "", *bench_table({**timings, **(c_rows or {})}, overhead), ""]
    for name, error in (not_built or {}).items():
        lines += [f"{name}: not built ({error}).", ""]
    if c_note:
        lines += [f"{c_note}.", ""]
    goal = goal_line(timings)
    if goal:
        lines += [goal, ""]
    lines += ["Step: wall and thread-CPU time around `step()`. Solver: the solver's own time "
              "(OSQP `solve_time` for the QP controllers, IPOPT `t_wall_total` for NMPC); "
              "solver share: the solver's time summed over the steps / the step wall time summed. Not solved: steps whose "
              "status was not SOLVED. Paper: average per step (MATLAB, CasADi / IPOPT, Intel i7 "
              "at 1.10 GHz)."]
    if NMPC_COMPILED_ROW in timings:
        lines += ["", f"{NMPC_COMPILED_ROW}: NMPC as the real-time ECU runs it, its NLP's functions "
                  "compiled once into a shared library (controller/nlp_library.py, docs/controllers.md) "
                  "instead of evaluated by CasADi's virtual machine; the same iterates (no budget here)."]
    if c_rows:
        lines += ["", "NAME (C): the C firmware's control step (libecu.so, `make firmware`; "
                  "docs/firmware.md) on the same samples, timed alternately with its Python twin in a "
                  "second pass (one C core per process); step wall: `ecu_step`'s own time measured inside "
                  "the C core (monotonic clock), without the Python call; step CPU: the thread CPU time of "
                  "the call through ctypes (an upper bound). `make bench-native` has the same measurement "
                  "with the call's wall time and the control task in real time."]
    if overhead is not None:
        tick = overhead["tick"]
        lines += ["", f"{ECU_OVERHEAD_ROW}: the ECU's control task with a one-line scripted law "
                  "(mode logic, guard, encode and TX of STEER_TORQUE_CMD and CTRL_DIAG), lockstep "
                  f"on a python-can virtual bus, fed the same samples ({overhead['control_task'].n} "
                  f"cycles, final mode {overhead['final_mode']}); an ECU cycle costs about a "
                  f"controller's step plus this. Per 5 ms tick (frames handled to HIL_SYNC_ACK): "
                  f"p50 {tick.p50_ms:.3f} / p99 {tick.p99_ms:.3f} / max {tick.max_ms:.3f} ms. "
                  "The deadlines, jitter and latency of the ECU in real time are `make timing`'s "
                  "(results/timing.md)."]
    if cadence:
        lines += ["", *cadence_table(cadence)]
    if cadence_note:
        lines += ["", f"{cadence_note}."]
    return "\n".join(lines) + "\n"


def as_json(timings: Mapping[str, ControllerTiming], overhead: Mapping[str, Any] | None,
            recording: str, command: str, load_start: tuple[float, float, float],
            load_end: tuple[float, float, float], not_built: Mapping[str, str] | None = None,
            c_rows: Mapping[str, ControllerTiming] | None = None, c_note: str | None = None,
            speed_ms: float = float("nan"), cadence: Sequence[CadenceRow] = (),
            cadence_note: str | None = None) -> dict[str, Any]:
    """Every figure of the report, JSON-ready (times in ms); the C core's rows under
    ``c_core`` (``note``: why some or all are missing); the cadence rows under ``cadence``."""
    return {
        "command": command, "machine": machine_description(), "node": platform.node(),
        "speed_reference_ms": speed_ms,
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "load_average_start": list(load_start), "load_average_end": list(load_end),
        "recording": recording, "baseline": BASELINE,
        "controllers": {name: dataclasses.asdict(t) for name, t in timings.items()},
        "not_built": dict(not_built or {}),
        "c_core": {"rows": {name: dataclasses.asdict(t) for name, t in (c_rows or {}).items()}, "note": c_note},
        "ecu_overhead": None if overhead is None else
        {key: dataclasses.asdict(value) if isinstance(value, Percentiles) else value
         for key, value in overhead.items()},
        "cadence": {"rows": cadence_json(cadence), "note": cadence_note},
    }


def profile_steps(name: str, samples: Sequence[VehicleSample], path: ReferencePath,
                  top: int = TOP_FUNCTIONS) -> str:
    """cProfile of ``name``'s steps on ``samples`` (the first left out): the ``top``
    functions by own time, as text."""
    from controller.registry import create_controller

    controller = create_controller(name)
    controller.set_path(path)
    profile = cProfile.Profile()
    for index, sample in enumerate(samples):
        if index:
            profile.enable()
        controller.step(sample)
        profile.disable()
    stream = io.StringIO()
    stats = pstats.Stats(profile, stream=stream)
    stats.sort_stats("tottime").print_stats(top)
    return f"cProfile of {name} `step()` x {len(samples) - 1} (own time; cProfile adds its " \
           f"own cost per call):\n{stream.getvalue()}"


def main(argv: list[str] | None = None) -> int:
    """Record, time, measure the ECU overhead, write the report; 0 on success."""
    parser = argparse.ArgumentParser(prog="python -m studies.bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=None,
                        help="record only this many control steps (default: the whole lane change)")
    parser.add_argument("--controllers", default=None,
                        help="comma-separated names (default: every name in the registry)")
    parser.add_argument("--no-ecu", action="store_true", help="leave out the ECU overhead")
    parser.add_argument("--no-c", action="store_true", help="leave out the C core's rows (make firmware)")
    parser.add_argument("--no-cadence", action="store_true",
                        help="leave out the step at the control cadence (studies/step_cadence.py)")
    parser.add_argument("--profile", metavar="NAME", default=None,
                        help="also print a cProfile of NAME's steps on the same samples; writes no file")
    parser.add_argument("--out", type=Path, default=Path("results/bench.md"))
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    args = parser.parse_args(argv)
    names = ([n.strip() for n in args.controllers.split(",") if n.strip()] if args.controllers
             else registered_names())
    unknown = sorted(set(names + ([args.profile] if args.profile else [])) - set(registered_names()))
    if unknown or not names:
        print(f"error: unknown controller(s) {unknown}; choose from "
              f"{', '.join(registered_names())}", file=sys.stderr)
        return 2
    command = "python -m studies.bench" + (f" --steps {args.steps}" if args.steps else "") + \
        (f" --controllers {','.join(names)}" if args.controllers else "") + \
        (" --no-ecu" if args.no_ecu else "") + (" --no-c" if args.no_c else "") + \
        (" --no-cadence" if args.no_cadence else "")
    load_start = load_average()
    speed_ms = speed_reference()  # with the load: the machine as the run found it
    not_built: dict[str, str] = {}
    try:
        samples, path, recording = record_samples(args.steps)
        controllers, not_built = build_controllers(names)
        timings = time_controllers(controllers, samples, path)
        c_rows, c_note = ({}, None) if args.no_c else c_core_timings(list(controllers), samples, path)
        overhead = None if args.no_ecu else measure_ecu_overhead(samples)
        cadence, cadence_note = ([], None) if args.no_cadence or GOAL_CONTROLLER not in controllers else \
            cadence_rows(GOAL_CONTROLLER, samples[:CADENCE_STEPS + 1], path, with_c=not args.no_c)
    except BenchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    finally:
        for name, error in not_built.items():
            print(f"error: {name} not built: {error}", file=sys.stderr)
    load_end = load_average()
    text = report(timings, overhead, recording, command, load_start, load_end, not_built, c_rows, c_note,
                  speed_ms=speed_ms, cadence=cadence, cadence_note=cadence_note)
    if args.profile:  # a look at one controller: printed, the committed report left alone
        print(text)
        print(profile_steps(args.profile, samples, path))
        return 1 if not_built else 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    written = [args.out]
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(as_json(timings, overhead, recording, command, load_start,
                                                load_end, not_built, c_rows, c_note, speed_ms, cadence,
                                                cadence_note),
                                        indent=2) + "\n")
        written.append(args.json)
    print(text)
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 1 if not_built else 0


if __name__ == "__main__":
    sys.exit(main())

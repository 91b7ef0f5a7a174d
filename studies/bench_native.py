"""``make bench-native``: the C control core's step against the Python controller's step.

    python -m studies.bench_native [--steps N] [--controllers eso-dkmpc,dkmpc,lmpc] [--repeats R]

The samples are those of ``make bench`` (``studies.step_timing.record_samples``: LMPC driving
the four-wheel plant through the high-mu double lane change). For each controller the
Python controller and the C core (``firmware_sim.native.NativeController``, libecu.so)
are fed the same samples alternately in one process (``studies.step_timing.time_controllers``:
open loop, the order rotated per sample, the first step left out). Two C figures: the
step as the C core times itself (``ecu_step`` alone: what an ECU would spend) and the
wall time of the Python call into it (ctypes and the result's conversion added).
The commands of both are compared as well: the largest difference is printed.

Each controller's pass over the samples is made ``--repeats`` R times (default 5), each
with freshly built controllers (so every pass does the same work, step by step). The
usual figures (p50 / p99 / max of every sample's time) are those of the first pass, as
with one pass. Beside them, the p99 over the samples of each sample's fastest time over
the R passes (``c_min_p99_us``, ``python_min_p99_us``): a preemption or a cache flush by
another process rarely hits the same sample in every pass, so this is the step's own cost
without the host's interference (the step's work still includes the caches the other
implementation's step empties in between).

Then, with ``--task-seconds N`` (default 10; 0 skips it), the C ECU executable and the
Python ECU each run ESO-DKMPC in real time for N s of the high-mu lane change as a
process on the socketcand hub of the timing tests (``run_on_hub``, also the harness of
tests/test_firmware_c_bus.py): the control task's own time as each ECU reports it in
CTRL_DIAG.CYCLE_TIME_US, and its overruns.

The last line is one JSON object: ``c_p50_us``, ``c_p99_us`` (the C core's own step
time of ESO-DKMPC), ``python_p50_us``, ``python_p99_us`` (the Python step's wall time),
``c_min_p99_us``, ``python_min_p99_us`` (the same, p99 of each sample's fastest of the
R passes), ``repeats``, per controller every figure, and the task figures
(``c_task_p99_us`` ...). Figures depend on the machine and its load.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402 (after the BLAS setting on purpose)
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402


import numpy as np  # noqa: E402

from controller.base import Command, Controller, StepDebug, VehicleSample  # noqa: E402
from controller.reference import ReferencePath  # noqa: E402
from firmware_sim.errors import EcuError  # noqa: E402
from firmware_sim.native import NATIVE_CONTROLLERS, NativeController  # noqa: E402
from studies.step_timing import (BenchError, ControllerTiming, Percentiles, record_samples,  # noqa: E402
                                 time_controllers)
from studies.machine import load_average, machine_description  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
#: The C ECU executable (make firmware).
DEFAULT_EXECUTABLE = ROOT / "build" / "firmware" / "ecu"
#: The socketcand channel every process opens on the hub.
CHANNEL = "vcan0"
#: The controller of the JSON line's four headline figures.
HEADLINE = "eso-dkmpc"
#: Issue 18's target for the C step's p99 (us).
TARGET_P99_US = 100.0


#: Passes over the samples per controller (``--repeats``): the per-sample minimum's R.
DEFAULT_REPEATS = 5


class _Recorded(Controller):
    """Passes every call to ``inner``; keeps each step's command, solver time, wall time of
    ``inner.step`` and, for the C core, its own step time (s)."""

    def __init__(self, inner: Controller) -> None:
        self.inner, self.name = inner, inner.name
        self.commands: list[Command] = []
        self.step_times_s: list[float] = []
        self.solve_times_s: list[float] = []
        self.wall_times_s: list[float] = []

    def set_path(self, path: ReferencePath) -> None:
        self.inner.set_path(path)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        started = time.perf_counter()
        command, debug = self.inner.step(sample)
        self.wall_times_s.append(time.perf_counter() - started)
        self.commands.append(command)
        self.step_times_s.append(getattr(self.inner, "last_step_time_s", float("nan")))
        self.solve_times_s.append(debug.solve_time_s)
        return command, debug


def ecu_command(which: str, controller: str, path: Path, port: int, time_base: str = "--lockstep",
                executable: Path = DEFAULT_EXECUTABLE,
                extra: tuple[str, ...] = ()) -> tuple[list[str], dict[str, str]]:
    """Command line and environment of the C ECU (``which`` "c": ``executable``) or the
    Python ECU ("python") as a process on the hub at ``port``; ``extra`` options of both
    CLIs (``--cpu``, ``--rt-priority``)."""
    if which == "c":
        return ([str(executable), "--interface", "socketcand", "--channel", CHANNEL, "--port", str(port), "--controller",
                 controller, "--path", f"1={path}", time_base, *extra], dict(os.environ))
    environment = dict(os.environ, CAN_CONFIG=json.dumps({"host": "127.0.0.1", "port": port, "tcp_tune": True}))
    return ([sys.executable, "-m", "firmware_sim", "--interface", "socketcand", "--channel", CHANNEL,
             "--controller", controller, "--path", f"1={path}", time_base, *extra], environment)


def run_on_hub(which: str, scenario_name: str, controller: str, log: Path, path_file: Path | None = None,
               faults: dict | None = None, jump: tuple[int, int] | None = None, realtime: bool = False,
               executable: Path = DEFAULT_EXECUTABLE, duration_s: float | None = None,
               extra: tuple[str, ...] = ()):
    """The scenario with one ECU process on a hub of its own: ``hil.rig.Rig`` runs plant,
    planner and time master (``hil``) here, the bus faults of ``faults`` (a ``[faults]``
    table) injected as ``hil run --faults`` does, ``jump`` = (from TICK ms, ahead ms) a
    jump of virtual time; ``realtime``: every node on the wall clock
    (``hil.time_master.RealTimeMaster``); ``duration_s``: shorter than the scenario;
    ``extra``: more ECU options. Returns (the monitor's raw frames (tick ms, ID, payload),
    tracking, exit status, the ECU's output)."""
    from hil.bus import BusConfig, private_virtual_channel
    from hil.ecu_runners import EcuProcess
    from hil.fault_buses import TimeShiftingBus
    from hil.faults import FaultSpec
    from hil.rig import Rig, RigHooks
    from hil.run_types import RunOptions
    from hil.scenario import load_scenario

    scenario = load_scenario(scenario_name)
    options = RunOptions(controller=controller, bus=BusConfig("virtual", private_virtual_channel("bench")),
                         lockstep=not realtime, handshake_timeout_s=60.0, ack_timeout_s=10.0,
                         faults=FaultSpec.from_mapping(faults) if faults else None, ecu_output=log)

    def start_ecu(rig: Rig) -> EcuProcess:
        command, environment = ecu_command(which, controller, path_file or scenario.path_file, rig.hub_port,
                                           "--realtime" if realtime else "--lockstep", executable, extra)
        return EcuProcess(scenario, options, command, environment)

    def before_run() -> None:
        if realtime:
            time.sleep(1.5 if which == "python" else 0.3)  # the ECU's start-up (imports, model)

    hooks = RigHooks(ecu=start_ecu, own_hub=True, before_run=before_run,
                     wrap_master_bus=None if jump is None else (lambda bus: TimeShiftingBus(bus, *jump)))
    rig = Rig(scenario, options, hooks)
    with rig:
        rig.run(min(scenario.duration_s, duration_s or scenario.duration_s))
        time.sleep(0.1)
    status = rig.ecu.process.returncode
    tracking = rig.result().tracking
    return rig.monitor.raw, tracking, status, log.read_text()


def _timed_pass(name: str, samples: Sequence[VehicleSample], path: ReferencePath
                ) -> tuple[dict[str, ControllerTiming], ControllerTiming, float, np.ndarray, np.ndarray]:
    """One pass of :func:`c_step_timing`, plus the per-step times (s, the first step left
    out, (n - 1,) each): the C core's own ``ecu_step`` time and the Python step's wall time."""
    from controller.registry import create_controller

    python = _Recorded(create_controller(name))
    native = _Recorded(NativeController(name))
    timings = time_controllers({"python": python, "c": native}, samples, path)
    own = np.array(native.step_times_s[1:])
    core = dataclasses.replace(timings["c"], name=f"{name} (C)", wall=Percentiles.of(own),
                               solver_share=float(np.sum(native.solve_times_s[1:]) / own.sum()))
    steer_difference = max(abs(a.steer_angle - b.steer_angle) for a, b in zip(python.commands, native.commands))
    return timings, core, steer_difference, own, np.array(python.wall_times_s[1:])


def c_step_timing(name: str, samples: Sequence[VehicleSample],
                  path: ReferencePath) -> tuple[dict[str, ControllerTiming], ControllerTiming, float]:
    """The Python controller ``name`` and its C core (libecu.so) fed ``samples`` alternately
    (``time_controllers``; one C core per process, so one controller at a time).

    Returns: the timings of both calls ("python", "c": the call through ctypes), the C
    core's own step as a ``ControllerTiming`` (wall: ``ecu_step``'s own time, the first
    step left out; CPU: the call's thread CPU time, an upper bound; solver share of its own
    time), and the largest steer difference C - Python (rad).

    Raises:
        firmware_sim.errors.EcuError: libecu.so or its data file is missing or refused.
    """
    timings, core, steer_difference, _, _ = _timed_pass(name, samples, path)
    return timings, core, steer_difference


def per_sample_min_p99_us(times_s: Sequence[np.ndarray]) -> float:
    """p99 over the samples of each sample's fastest time (us); ``times_s``: one (n,) array
    of step times (s) per pass, the same samples in the same order."""
    return float(np.percentile(np.min(np.stack(times_s), axis=0), 99)) * 1e6


def bench_one(name: str, samples: Sequence[VehicleSample], path: ReferencePath,
              repeats: int = DEFAULT_REPEATS) -> dict[str, float]:
    """Python and C steps of controller ``name`` on ``samples`` in ``repeats`` passes, figures
    in us: those of the first pass, and the p99 of each sample's fastest time over all."""
    passes = [_timed_pass(name, samples, path) for _ in range(repeats)]
    timings, core, _, _, _ = passes[0]
    steer_difference = max(p[2] for p in passes)
    return {"c_p50_us": core.wall.p50_ms * 1e3, "c_p99_us": core.wall.p99_ms * 1e3,
            "c_min_p99_us": per_sample_min_p99_us([p[3] for p in passes]),
            "python_min_p99_us": per_sample_min_p99_us([p[4] for p in passes]), "repeats": repeats,
            "c_max_us": core.wall.max_ms * 1e3,
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


def task_times(seconds: float, controller: str = HEADLINE) -> dict[str, float]:
    """Both ECUs in real time on the hub (``run_on_hub``) through the high-mu lane change
    for ``seconds``: the control task's own time from CTRL_DIAG.CYCLE_TIME_US (us; the
    first second, start-up, left out) and the ECU's overrun count."""
    import tempfile

    from can_defs.codec import decode
    from can_defs.frames import FrameId

    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as folder:
        for which in ("python", "c"):
            raw, _, status, output = run_on_hub(which, "dlc_high_mu", controller, Path(folder) / f"{which}.log",
                                                realtime=True, duration_s=seconds)
            if status != 0:
                raise BenchError(f"{which} ECU on the hub exited {status}: {output[-500:]}")
            diags = [(tick, decode(i, d).frame) for tick, i, d in raw if i == FrameId.CTRL_DIAG]
            cycle = np.array([float(f.cycle_time_us) for tick, f in diags if tick >= 1000])
            if cycle.size == 0:
                raise BenchError(f"{which} ECU sent no CTRL_DIAG after the first second")
            figures[f"{which}_task_p50_us"] = float(np.percentile(cycle, 50))
            figures[f"{which}_task_p99_us"] = float(np.percentile(cycle, 99))
            figures[f"{which}_task_max_us"] = float(cycle.max())
            figures[f"{which}_task_overruns"] = float(max(f.overruns for _, f in diags))
            figures[f"{which}_task_cycles"] = float(cycle.size)
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=None, help="only the first N control steps")
    parser.add_argument("--controllers", default=",".join(NATIVE_CONTROLLERS),
                        help=f"comma-separated, of {', '.join(NATIVE_CONTROLLERS)}")
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS,
                        help="passes over the samples per controller; c_min_p99_us / python_min_p99_us: "
                             "p99 of each sample's fastest pass (default %(default)s)")
    parser.add_argument("--task-seconds", type=float, default=10.0,
                        help="seconds of each ECU in real time on the hub for the control task's time "
                             "(0: skip)")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    unknown = [n for n in names if n not in NATIVE_CONTROLLERS]
    if unknown or not names:
        print(f"error: --controllers: {', '.join(unknown) or '(none)'} not in the C core "
              f"({', '.join(NATIVE_CONTROLLERS)})", file=sys.stderr)
        return 2
    if args.repeats < 1:
        print(f"error: --repeats {args.repeats}: at least 1", file=sys.stderr)
        return 2
    try:
        load_start = load_average()
        samples, path, description = record_samples(args.steps)
        results = {name: bench_one(name, samples, path, args.repeats) for name in names}
        tasks = task_times(args.task_seconds) if args.task_seconds > 0 else {}
    except (BenchError, EcuError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{description}; {machine_description()}; load average {load_start[0]:.2f} at the start, "
          f"{load_average()[0]:.2f} at the end")
    print(f"{'controller':<10} {'C p50':>7} {'C p99':>7} {'C minp99':>8} {'C max':>7} {'call p99':>8} "
          f"{'cpu p99':>8} {'Py p50':>7} {'Py p99':>7} {'Py minp99':>9} {'Py cpu p99':>10}")
    for name, r in results.items():
        print(f"{name:<10} {r['c_p50_us']:7.1f} {r['c_p99_us']:7.1f} {r['c_min_p99_us']:8.1f} {r['c_max_us']:7.1f} "
              f"{r['c_call_p99_us']:8.1f} {r['c_call_cpu_p99_us']:8.1f} {r['python_p50_us']:7.1f} "
              f"{r['python_p99_us']:7.1f} {r['python_min_p99_us']:9.1f} {r['python_cpu_p99_us']:10.1f}  "
              f"max |steer C - Python| {r['max_steer_difference_rad']:.1e} rad")
    print(f"(us. C: ecu_step's own wall time; call: the Python call into it through ctypes, wall and "
          f"thread CPU time; Py: the Python controller's step, wall and CPU time; p50 / p99 / max of the first "
          f"pass; minp99: p99 of each sample's fastest of {args.repeats} passes, the step without the host's "
          f"interference)")
    head = results.get(HEADLINE) or next(iter(results.values()))
    headline_name = HEADLINE if HEADLINE in results else next(iter(results))
    verdict = "met" if head["c_p99_us"] <= TARGET_P99_US else "NOT met"
    print(f"target: {headline_name} C step p99 <= {TARGET_P99_US:.0f} us: {verdict} ({head['c_p99_us']:.1f} us; "
          f"each sample's fastest of {args.repeats} passes: p99 {head['c_min_p99_us']:.1f} us)")
    if tasks:
        print(f"control task in real time on the hub, {HEADLINE}, {args.task_seconds:g} s of dlc_high_mu "
              f"(CTRL_DIAG.CYCLE_TIME_US, first second left out): C p50 {tasks['c_task_p50_us']:.0f} us, "
              f"p99 {tasks['c_task_p99_us']:.0f} us, {tasks['c_task_overruns']:.0f} overruns; Python p50 "
              f"{tasks['python_task_p50_us']:.0f} us, p99 {tasks['python_task_p99_us']:.0f} us, "
              f"{tasks['python_task_overruns']:.0f} overruns")
    summary = {key: head[key] for key in ("c_p50_us", "c_p99_us", "python_p50_us", "python_p99_us",
                                          "c_min_p99_us", "python_min_p99_us", "repeats")}
    summary.update(controller=headline_name, controllers=results, **tasks)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

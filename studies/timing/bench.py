"""``make timing``: the ECU's deadlines, jitter and latency, as on a vehicle (issue 9).

    python -m studies.timing.bench [--seconds 120] [--nmpc-seconds 30]
        [--controllers eso-dkmpc,dkmpc,lmpc,nmpc] [--c-controllers eso-dkmpc,dkmpc,lmpc]
        [--conditions idle,stress]
        [--scheduling rt|normal] [--cpu-latency hold|default]
        [--out results/timing.md] [--work build/timing]

For each load condition (``idle``; ``stress``: a busy loop pinned to each core, see
`studies.timing.stress`) and each controller, `studies.timing.runner.run_timing` runs the ECU
(CPU 0, SCHED_FIFO 50) against the plant (CPU 1, SCHED_FIFO 40) over the loopback CAN
hub, 40 Hz control for ``--seconds`` (default ``TIMING_SECONDS`` from the environment,
else 120 s); NMPC for ``--nmpc-seconds`` only, as it does not keep up with 25 ms.
Then the C ECU executable (issue 18, ``make firmware``) with each of ``--c-controllers``
under the same conditions and options, rows "NAME (C)" (``--c-controllers none``: left out).
The whole benchmark holds a CPU latency request of 0 us (`studies.timing.cpu_latency`, as
cyclictest does) unless ``--cpu-latency default``. Writes the Markdown report, one histogram PNG per condition (``<out stem>_<condition>.png``)
and ``summary.json`` plus each run's raw files under ``--work``.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from hil.errors import HilError  # noqa: E402
from studies.timing.cpu_latency import CpuLatencyRequest  # noqa: E402
from studies.timing.report import (SETTLE_S, RunFigures, as_json, goal_lines,  # noqa: E402
                               percentile_table, plot_histograms, run_figures, summary_table)
from studies.timing.runner import Placement, ecu_label, run_timing  # noqa: E402
from studies.timing.stress import BUSY_LOOP, StressLoad  # noqa: E402

CONDITIONS = ("idle", "stress")
CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
#: The controllers of the C ECU executable (no NMPC).
C_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")


def default_seconds() -> float:
    """``TIMING_SECONDS`` from the environment, else 120 s.

    Raises:
        ValueError: ``TIMING_SECONDS`` is not a positive number.
    """
    text = os.environ.get("TIMING_SECONDS", "120")
    try:
        seconds = float(text)
    except ValueError:
        raise ValueError(f"TIMING_SECONDS={text!r} is not a number of seconds") from None
    if not seconds > 0:
        raise ValueError(f"TIMING_SECONDS={text!r} must be > 0")
    return seconds


def _names(text: str, allowed: tuple[str, ...], what: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in allowed]
    if unknown or not names:
        raise ValueError(f"--{what}: unknown {unknown or 'empty list'}; choose from "
                         f"{', '.join(allowed)}")
    return names


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the report; ``error: ...`` and exit 1 on failure."""
    parser = argparse.ArgumentParser(prog="python -m studies.timing.bench",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=None,
                        help="run length per controller (default TIMING_SECONDS, else 120)")
    parser.add_argument("--nmpc-seconds", type=float, default=30.0,
                        help="run length for nmpc (at most --seconds)")
    parser.add_argument("--controllers", default=",".join(CONTROLLERS))
    parser.add_argument("--c-controllers", default=",".join(C_CONTROLLERS),
                        help="controllers of the C ECU executable (make firmware) to run as well; "
                             "none: only the Python ECU")
    parser.add_argument("--conditions", default=",".join(CONDITIONS))
    parser.add_argument("--scheduling", choices=("rt", "normal"), default="rt",
                        help="rt: ECU and plant pinned to separate cores under SCHED_FIFO "
                             "(default); normal: no pinning, SCHED_OTHER (for comparison)")
    parser.add_argument("--cpu-latency", choices=("hold", "default"), default="hold",
                        help="hold: a CPU latency request of 0 us (/dev/cpu_dma_latency, as "
                             "cyclictest) for the whole benchmark, so idle cores poll instead of "
                             "halting (default); default: the machine's idle states")
    parser.add_argument("--release", choices=("clock", "sample"), default="clock",
                        help="what releases the ECU's control task: clock (contract revision 2, "
                             "default) or sample (revision 3, docs/can-contract.md)")
    parser.add_argument("--out", type=Path, default=Path("results/timing.md"))
    parser.add_argument("--work", type=Path, default=Path("build/timing"))
    args = parser.parse_args(argv)
    try:
        seconds = args.seconds if args.seconds is not None else default_seconds()
        controllers = _names(args.controllers, CONTROLLERS, "controllers")
        c_controllers = [] if args.c_controllers.strip() == "none" else \
            _names(args.c_controllers, C_CONTROLLERS, "c-controllers")
        conditions = _names(args.conditions, CONDITIONS, "conditions")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    placement = Placement.for_this_machine() if args.scheduling == "rt" \
        else Placement(None, None, None, None, None)
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    figures: list[RunFigures] = []
    loads: dict[str, str] = {}
    stress_pinning: list[str] = []
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with CpuLatencyRequest(0, requested=args.cpu_latency == "hold") as latency:
        for condition in conditions:
            load_before = os.getloadavg()
            with StressLoad(cpus if condition == "stress" else ()) as stress:
                stress_pinning = stress_pinning or stress.pinned
                for controller, ecu in [*((c, "python") for c in controllers),
                                        *((c, "c") for c in c_controllers)]:
                    run_seconds = min(seconds, args.nmpc_seconds) if controller == "nmpc" else seconds
                    label = ecu_label(controller, ecu)
                    print(f"{condition} / {label}: {run_seconds:g} s ...", flush=True)
                    try:
                        run = run_timing(controller, run_seconds, args.work /
                                         f"{condition}__{controller}{'_c' if ecu == 'c' else ''}",
                                         placement, ecu, args.release)
                    except HilError as e:
                        print(f"error: {condition} / {label}: {e}", file=sys.stderr)
                        return 1
                    figures.append(run_figures(run, condition))
                    print("\n".join(summary_table(figures[-1:])[2:]), flush=True)
            load_after = os.getloadavg()
            loads[condition] = (f"load average (1 min) {load_before[0]:.2f} before, "
                                f"{load_after[0]:.2f} after")
        idle_states = latency.describe()
    pngs = [plot_histograms(figures, condition,
                            args.out.with_name(f"{args.out.stem}_{condition}.png"))
            for condition in conditions]
    args.work.mkdir(parents=True, exist_ok=True)
    (args.work / "summary.json").write_text(json.dumps(as_json(figures), indent=1) + "\n")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(_report(figures, seconds, args, started, loads,
                                          stress_pinning, pngs, idle_states)) + "\n")
    print(f"wrote {args.out}, {', '.join(map(str, pngs))}")
    return 0


def _report(figures: list[RunFigures], seconds: float, args: argparse.Namespace, started: str,
            loads: dict[str, str], stress_pinning: list[str], pngs: list[Path],
            idle_states: str) -> list[str]:
    scheduling = figures[0].scheduling if figures else {}
    lines = [
        "# ECU timing (issue 9)", "",
        f"`python -m studies.timing.bench --seconds {seconds:g} --nmpc-seconds {args.nmpc_seconds:g}"
        f"{'' if args.c_controllers == ','.join(C_CONTROLLERS) else f' --c-controllers {args.c_controllers}'}"
        f"{'' if args.cpu_latency == 'hold' else f' --cpu-latency {args.cpu_latency}'}` "
        f"(`make timing`), started {started} on `{platform.node()}` "
        f"({platform.processor() or platform.machine()}, {os.cpu_count()} CPUs).", "",
        "- Transport: python-can's `socketcand` interface (TCP_NODELAY) to `hil.timing.hub`, a "
        "socketcand-protocol CAN hub on 127.0.0.1 (loopback only; the host kernel has no "
        "SocketCAN vcan0). Each frame crosses two TCP loopback hops (sender -> hub -> receiver).",
        f"- Scheduling obtained: ECU {scheduling.get('ecu', '?')}; plant "
        f"{scheduling.get('plant', '?')}; hub {scheduling.get('hub', '?')}.",
        f"- CPU idle states: CPU latency request {idle_states}, for all runs alike "
        "(`studies/timing/cpu_latency.py`: held, an idle core polls instead of halting its vCPU; "
        "`--cpu-latency default` leaves the idle states as they are).",
        "- Load conditions: `idle` = nothing of ours besides the run (other jobs on the shared "
        "machine may run: see the load averages); `stress` = one busy-loop process per core "
        f"(`{BUSY_LOOP.strip().splitlines()[-1].strip()}` forever, SCHED_OTHER nice 0, "
        f"pinned: {', '.join(stress_pinning) or 'n/a'}).",
        *(f"- {condition}: {text}" for condition, text in loads.items()),
        "- ECUs: rows NAME are the Python ECU (`python -m firmware_sim`), rows NAME (C) the C ECU "
        "executable (`build/firmware/ecu`, docs/firmware.md), both started with the same options "
        "and writing the same per-cycle record.",
        f"- Plant: four-wheel model, 5 ms ticks on absolute deadlines, frames every 10 ms; "
        f"35 km/h, mu 0.85, repeated double lane changes. Window: from {SETTLE_S:g} s after the "
        "plant started to its end (the ECU's own CLOCK_MONOTONIC stamps).",
        "- Figures (ECU's per-cycle record, `firmware_sim/timing.py`): release jitter = task "
        "start - ideal release; task time = the whole control task; solver time = the QP / NLP "
        "solver's own statistic (cycles in ACTIVE / DEGRADED only); input age = task start - arrival of the newest plant sample; "
        "RX-to-TX latency = that arrival -> TX of the command. Overruns: tasks not finished at "
        "the next release plus skipped releases. Commands lost: alive-counter gaps of "
        "STEER_TORQUE_CMD at the plant (E2E receiver).",
        "- CPU steal (from /proc/stat over the plant's run): time the hypervisor ran other work "
        "while this virtual machine had work ready. SCHED_FIFO inside the guest cannot protect "
        "the ECU from it; with both vCPUs busy (the stress condition) this VM is given about "
        "one core's worth of time, so steal reaches ~50 % and FIFO tasks stall for whole host "
        "time slices.", "",
        "## Summary", "", *summary_table(figures), "",
        "## Goals", "", *goal_lines(figures), "",
        "The plant publishes every 10 ms, unsynchronised with the ECU's 25 ms releases, so the "
        "newest sample is on average ~5 ms old when a task starts and the RX-to-TX latency as "
        "defined (sample arrival to command TX) is that age plus the task time: a time-triggered "
        "ECU can only bring it under 3 ms by releasing its task on the arrival of a sample.", "",
        "## Percentiles (ms)", "", *percentile_table(figures), "",
        "## Histograms", "", *(f"![{png.stem}]({png.name})" for png in pngs), "",
    ]
    return lines


if __name__ == "__main__":
    sys.exit(main())

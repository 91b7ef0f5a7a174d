"""``make timing``: the ECU's deadlines, jitter and latency, as on a vehicle (issues 9, 37).

    python -m studies.timing.bench [--seconds 45] [--nmpc-seconds 30]
        [--controllers eso-dkmpc,dkmpc,lmpc,nmpc] [--c-controllers eso-dkmpc,dkmpc,lmpc]
        [--conditions idle,stress] [--release clock,sample] [--repeats 3]
        [--scheduling rt|normal] [--cpu-latency hold|default]
        [--out results/timing.md] [--work build/timing]

For each load condition (``idle``; ``stress``: a busy loop pinned to each core, see
`studies.timing.stress`), `studies.timing.runner.run_timing` runs the ECU (CPU 0,
SCHED_FIFO 50) against the plant (CPU 1, SCHED_FIFO 40) over the loopback CAN hub, 40 Hz
control for ``--seconds`` per run (default ``TIMING_SECONDS`` from the environment, else
45 s); NMPC for ``--nmpc-seconds`` only, as it does not keep up with 25 ms. The runs
(`studies.timing.plan`): ESO-DKMPC on the Python ECU and on the C ECU executable (issue 18,
``make firmware``; rows "NAME (C)") under every ``--release`` (clock: contract revision 2;
sample: revision 3), ``--repeats`` times each, interleaved; then the other ``--controllers``
and ``--c-controllers`` once under the first release (``--c-controllers none``: no C ECU).
The whole benchmark holds a CPU latency request of 0 us (`studies.timing.cpu_latency`, as
cyclictest does) unless ``--cpu-latency default``. Writes the Markdown report (goals of
issue 37, run-to-run spread, every run; `studies.timing.goals`, `studies.timing.report`),
one histogram PNG per condition (``<out stem>_<condition>.png``) and ``summary.json`` plus
each run's raw files under ``--work``.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

from hil.errors import HilError  # noqa: E402
from studies.speed_reference import speed_reference  # noqa: E402
from studies.timing.cpu_latency import CpuLatencyRequest  # noqa: E402
from studies.timing.goals import goal_lines, spread_table  # noqa: E402
from studies.timing.plan import (REPEATED_CONTROLLER, RELEASES, RunSpec,  # noqa: E402
                                 estimated_seconds, parse_releases, plan_runs)
from studies.timing.report import (SETTLE_S, RunFigures, as_json,  # noqa: E402
                                   percentile_table, plot_histograms, run_figures, summary_table)
from studies.timing.runner import Placement, run_timing  # noqa: E402
from studies.timing.stress import BUSY_LOOP, StressLoad  # noqa: E402

CONDITIONS = ("idle", "stress")
CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
#: The controllers of the C ECU executable (no NMPC).
C_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: Seconds per run without --seconds or TIMING_SECONDS: the default benchmark's 34 runs
#: (`studies.timing.plan`: 2 x 17, with NMPC at 30 s) then take about 28 min on the 2-core
#: machine (`plan.estimated_seconds`, printed at the start).
DEFAULT_SECONDS = 45.0
#: Runs of each ESO-DKMPC row (per ECU and release) for the run-to-run spread.
DEFAULT_REPEATS = 3


def default_seconds() -> float:
    """``TIMING_SECONDS`` from the environment, else `DEFAULT_SECONDS`.

    Raises:
        ValueError: ``TIMING_SECONDS`` is not a positive number.
    """
    text = os.environ.get("TIMING_SECONDS", f"{DEFAULT_SECONDS:g}")
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
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(prog="python -m studies.timing.bench",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=None,
                        help=f"run length of every run (default TIMING_SECONDS, else "
                             f"{DEFAULT_SECONDS:g})")
    parser.add_argument("--nmpc-seconds", type=float, default=30.0,
                        help="run length for nmpc (at most --seconds)")
    parser.add_argument("--controllers", default=",".join(CONTROLLERS))
    parser.add_argument("--c-controllers", default=",".join(C_CONTROLLERS),
                        help="controllers of the C ECU executable (make firmware) to run as well; "
                             "none: only the Python ECU")
    parser.add_argument("--conditions", default=",".join(CONDITIONS))
    parser.add_argument("--release", default=",".join(RELEASES),
                        help="what releases the ECU's control task, comma-separated: clock "
                             "(contract revision 2) and / or sample (revision 3, "
                             "docs/can-contract.md). The eso-dkmpc rows run under each; the other "
                             "controllers under the first (default clock,sample)")
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS,
                        help="runs of each eso-dkmpc row (per ECU and release), for the "
                             f"run-to-run spread (default {DEFAULT_REPEATS})")
    parser.add_argument("--scheduling", choices=("rt", "normal"), default="rt",
                        help="rt: ECU and plant pinned to separate cores under SCHED_FIFO "
                             "(default); normal: no pinning, SCHED_OTHER (for comparison)")
    parser.add_argument("--cpu-latency", choices=("hold", "default"), default="hold",
                        help="hold: a CPU latency request of 0 us (/dev/cpu_dma_latency, as "
                             "cyclictest) for the whole benchmark, so idle cores poll instead of "
                             "halting (default); default: the machine's idle states")
    parser.add_argument("--out", type=Path, default=Path("results/timing.md"))
    parser.add_argument("--work", type=Path, default=Path("build/timing"))
    args = parser.parse_args(argv)
    try:
        seconds = args.seconds if args.seconds is not None else default_seconds()
        controllers = _names(args.controllers, CONTROLLERS, "controllers")
        c_controllers = [] if args.c_controllers.strip() == "none" else \
            _names(args.c_controllers, C_CONTROLLERS, "c-controllers")
        conditions = _names(args.conditions, CONDITIONS, "conditions")
        plan = plan_runs(controllers, c_controllers, parse_releases(args.release), args.repeats,
                         seconds, args.nmpc_seconds)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    estimate = estimated_seconds(plan, len(conditions))
    print(f"{len(plan) * len(conditions)} runs, about {estimate / 60:.0f} min", flush=True)
    placement = Placement.for_this_machine() if args.scheduling == "rt" \
        else Placement(None, None, None, None, None)
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    figures: list[RunFigures] = []
    loads: dict[str, str] = {}
    stress_pinning: list[str] = []
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    speed = speed_reference()  # before any run: the machine idle as the idle runs see it
    wall_start = time.monotonic()
    with CpuLatencyRequest(0, requested=args.cpu_latency == "hold") as latency:
        for condition in conditions:
            load_before = os.getloadavg()
            with StressLoad(cpus if condition == "stress" else ()) as stress:
                stress_pinning = stress_pinning or stress.pinned
                for spec in plan:
                    name = f"{condition} / {spec.label} / {spec.release} / run {spec.repeat}"
                    print(f"{name}: {spec.seconds:g} s ...", flush=True)
                    try:
                        run = run_timing(spec.controller, spec.seconds,
                                         args.work / spec.work_name(condition), placement,
                                         spec.ecu, spec.release)
                    except HilError as e:
                        print(f"error: {name}: {e}", file=sys.stderr)
                        return 1
                    figures.append(run_figures(run, condition, repeat=spec.repeat))
                    print("\n".join(summary_table(figures[-1:])[2:]), flush=True)
            load_after = os.getloadavg()
            loads[condition] = (f"load average (1 min) {load_before[0]:.2f} before, "
                                f"{load_after[0]:.2f} after")
        idle_states = latency.describe()
    wall_s = time.monotonic() - wall_start
    figures = grouped(figures)
    pngs = [plot_histograms(figures, condition,
                            args.out.with_name(f"{args.out.stem}_{condition}.png"))
            for condition in conditions]
    args.work.mkdir(parents=True, exist_ok=True)
    (args.work / "summary.json").write_text(json.dumps(as_json(figures), indent=1) + "\n")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    context = ReportContext(argv=argv, plan=plan, started=started, wall_s=wall_s, loads=loads,
                            stress_pinning=stress_pinning, pngs=pngs, idle_states=idle_states,
                            speed_reference_ms=speed)
    args.out.write_text("\n".join(_report(figures, context)) + "\n")
    print(f"wrote {args.out}, {', '.join(map(str, pngs))} ({wall_s / 60:.1f} min)")
    return 0


def grouped(figures: list[RunFigures]) -> list[RunFigures]:
    """``figures`` reordered for the tables: by load condition, then row (controller label
    and release, in the order first run), then repeat; the run order interleaves repeats."""
    first: dict[tuple[str, str, str], int] = {}
    for i, f in enumerate(figures):
        first.setdefault((f.condition, f.controller, f.release), i)
    return sorted(figures, key=lambda f: (first[(f.condition, f.controller, f.release)],
                                          f.repeat))


@dataclass(frozen=True)
class ReportContext:
    """What the report states besides the figures: the command line, the plan of one load
    condition, when it started and how long it took, the loads, the stress pinning, the
    histogram files and the CPU idle states."""

    argv: list[str]
    plan: list[RunSpec]
    started: str
    wall_s: float
    loads: dict[str, str]
    stress_pinning: list[str]
    pngs: list[Path]
    idle_states: str
    speed_reference_ms: float = float("nan")


def durations_line(plan: list[RunSpec], conditions: int, wall_s: float) -> str:
    """The report's line on the run lengths: per row kind its seconds and repeats, the
    number of runs and the whole benchmark's wall time."""
    repeated = [s for s in plan if s.controller == REPEATED_CONTROLLER]
    others = [s for s in plan if s.controller != REPEATED_CONTROLLER]
    parts = []
    if repeated:
        repeats = max(s.repeat for s in repeated)
        releases = ", ".join(dict.fromkeys(s.release for s in repeated))
        parts.append(f"{REPEATED_CONTROLLER} rows {repeated[0].seconds:g} s per run, "
                     f"{repeats} run{'s' if repeats > 1 else ''} per ECU and release ({releases})")
    for seconds in dict.fromkeys(s.seconds for s in others):
        names = ", ".join(s.label for s in others if s.seconds == seconds)
        parts.append(f"{names}: {seconds:g} s, one run ({others[0].release} release)")
    return (f"- Run lengths: {'; '.join(parts)}. {len(plan) * conditions} runs in all, "
            f"{wall_s / 60:.1f} min of wall time (start-up included).")


def _report(figures: list[RunFigures], context: ReportContext) -> list[str]:
    scheduling = figures[0].scheduling if figures else {}
    conditions = list(dict.fromkeys(f.condition for f in figures))
    command = shlex.join(["python", "-m", "studies.timing.bench", *context.argv])
    lines = [
        "# ECU timing (issues 9, 37)", "",
        f"`{command}` (`make timing`), started {context.started} on `{platform.node()}` "
        f"({platform.processor() or platform.machine()}, {os.cpu_count()} CPUs).", "",
        f"- Speed reference: {context.speed_reference_ms:.2f} ms before the first run (a fixed "
        "workload, the fastest of 7 runs, `studies/speed_reference.py`; `make bench` states it too): a "
        "virtual machine's CPU name does not say how fast its host is, so compare figures "
        "between results files only where this one is alike.",
        durations_line(context.plan, len(conditions), context.wall_s),
        "- Release: what released the ECU's control task (docs/can-contract.md): `clock` = the "
        "ECU's own 25 ms clock (contract revision 2, the ECUs' default); `sample` = the arrival of "
        "a complete good plant sample set in the window of each 25 ms control instant, with the "
        "period watchdog at +7.5 ms (revision 3, `--release sample`). Both with the plant of "
        "revision 2 (samples every 10 ms).",
        "- Transport: python-can's `socketcand` interface (TCP_NODELAY) to `hil.timing.hub`, a "
        "socketcand-protocol CAN hub on 127.0.0.1 (loopback only; the host kernel has no "
        "SocketCAN vcan0). Each frame crosses two TCP loopback hops (sender -> hub -> receiver).",
        f"- Scheduling obtained: ECU {scheduling.get('ecu', '?')}; plant "
        f"{scheduling.get('plant', '?')}; hub {scheduling.get('hub', '?')}.",
        f"- CPU idle states: CPU latency request {context.idle_states}, for all runs alike "
        "(`studies/timing/cpu_latency.py`: held, an idle core polls instead of halting its vCPU; "
        "`--cpu-latency default` leaves the idle states as they are).",
        "- Load conditions: `idle` = nothing of ours besides the run (other jobs on the shared "
        "machine may run: see the load averages); `stress` = one busy-loop process per core "
        f"(`{BUSY_LOOP.strip().splitlines()[-1].strip()}` forever, SCHED_OTHER nice 0, "
        f"pinned: {', '.join(context.stress_pinning) or 'n/a'}).",
        *(f"- {condition}: {text}" for condition, text in context.loads.items()),
        "- ECUs: rows NAME are the Python ECU (`python -m firmware_sim`), rows NAME (C) the C ECU "
        "executable (`build/firmware/ecu`, docs/firmware.md), both started with the same options "
        "and writing the same per-cycle record.",
        f"- Plant: four-wheel model, 5 ms ticks on absolute deadlines, frames every 10 ms; "
        f"35 km/h, mu 0.85, repeated double lane changes. Window: from {SETTLE_S:g} s after the "
        "plant started to its end (the ECU's own CLOCK_MONOTONIC stamps).",
        "- Figures (ECU's per-cycle record, `firmware_sim/timing.py`): release jitter = task "
        "start - ideal release (with the sample release: the release minus its control instant, "
        "0 and +5 ms alternating with a 10 ms plant, +7.5 ms or more for the watchdog: the "
        "watchdog releases column counts those cycles); task time "
        "= the whole control task; solver time = the QP / NLP solver's own statistic (cycles in "
        "ACTIVE / DEGRADED only); input age = task start - arrival of the newest plant sample; "
        "RX-to-TX latency = that arrival -> TX of the command. Overruns: tasks not finished at "
        "the next release plus skipped releases. Commands lost: alive-counter gaps of "
        "STEER_TORQUE_CMD at the plant (E2E receiver). The largest command gap at the plant is "
        "about 30 ms with the sample release by design (releases 20 and 30 ms apart with a "
        "10 ms plant).",
        "- CPU steal (from /proc/stat over the plant's run): time the hypervisor ran other work "
        "while this virtual machine had work ready. SCHED_FIFO inside the guest cannot protect "
        "the ECU from it; with both vCPUs busy (the stress condition) this VM is given about "
        "one core's worth of time, so steal reaches ~50 % and FIFO tasks stall for whole host "
        "time slices.", "",
        "## Goals (issue 37)", "",
        "A goal on a p99 is met only when every run of its row meets it; the line gives how "
        "many did and the p99's min / median / max over the runs.", "",
        *goal_lines(figures), "",
        "With the clock release the plant's 10 ms samples are unsynchronised with the ECU's "
        "25 ms releases, so the newest sample is 0-10 ms old when a task starts and the "
        "RX-to-TX latency (sample arrival to command TX) is that age plus the task time. With "
        "the sample release the task starts on the sample's arrival: the latency is the time "
        "to take the frame in plus the task time.", "",
        "## Run-to-run spread", "",
        "Per repeated row, the p99 of each run, min / median / max over its runs (ms):", "",
        *spread_table(figures), "",
        # the heading "Summary" is what the README's builder includes (@include ...#Summary)
        "## Summary", "", *summary_table(figures), "",
        "## Percentiles (ms)", "", *percentile_table(figures), "",
        "## Histograms", "", *(f"![{png.stem}]({png.name})" for png in context.pngs), "",
    ]
    return lines


if __name__ == "__main__":
    sys.exit(main())

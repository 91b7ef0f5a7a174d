"""``make run``: the paper's two double lane changes with the four controllers, over CAN.

Each run is ``hil.session.run_hil``: the ECU (firmware_sim) and the plant emulator,
planner and time master exchange only CAN frames, in lockstep. By default on python-can's
``virtual`` bus in one process (no set-up); with ``--interface socketcan --channel vcan0``
(``make run CAN_INTERFACE=socketcan CAN_CHANNEL=vcan0``) the ECU is a separate process on
a real SocketCAN bus.

Writes (``--out``, default ``results/``):

- ``run_table2_high_mu.md``, ``run_table3_low_mu.md``: e_Y / heading error Max / Avg /
  RMSE per controller over CAN (studies/report.py's layout, the paper's values beside);
- ``run_fig8_high_mu.png``, ``run_fig9_low_mu.png``: speed, steer, trajectory, e_Y;
- ``run_metrics.json``: every run's summary, without what depends on the machine, so
  that rerunning ``make run`` on any machine writes the same bytes;
- ``--logs`` (default ``results/logs/``, not under version control): every frame of every
  run, candump ``.log``, and ``run_timing.json``: the machine-dependent part of each run's
  summary (wall time, the ECU's task and solver times, overruns).

Exit status 0 when every run completed, 1 otherwise, 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from hil.bus import resolve_bus_config
from hil.errors import HilError

CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
#: Output names per scenario: (table, figure, title).
OUTPUTS = {
    "dlc_high_mu": ("run_table2_high_mu.md", "run_fig8_high_mu.png",
                    "Table II over CAN: constant 35 km/h, high-mu road (mu = 0.85)"),
    "dlc_low_mu": ("run_table3_low_mu.md", "run_fig9_low_mu.png",
                   "Table III over CAN: 45-55 km/h, low-mu road (mu = 0.5)"),
}


def _outputs(scenario_name: str) -> tuple[str, str, str]:
    return OUTPUTS.get(scenario_name, (f"run_table_{scenario_name}.md",
                                       f"run_fig_{scenario_name}.png", scenario_name))


def report_trace(result: Any, path: Any, target_speed: Any) -> Any:
    """A ``studies.closed_loop.ClosedLoopTrace`` of an over-CAN run at its control instants
    (what studies/report.py plots): plant truth from the plant node, solver facts from
    CTRL_DIAG; fields the bus does not carry are NaN."""
    from studies.closed_loop import ClosedLoopTrace
    from hil.metrics import path_errors

    plant, ecu = result.plant_trace, result.ecu_trace
    time_ms = np.round(plant["time"] * 1000).astype(np.int64)
    rows = time_ms % 25 == 0
    n = int(rows.sum())
    errors = path_errors(np.column_stack([plant["x"][rows], plant["y"][rows], plant["yaw"][rows]]),
                         path)
    by_tick = {int(round(t * 1000)): i for i, t in enumerate(ecu["time"])}
    index = np.array([by_tick.get(int(t), -1) for t in time_ms[rows]])

    def from_ecu(name: str, scale: float = 1.0) -> np.ndarray:
        values = np.full(n, np.nan)
        found = index >= 0
        values[found] = ecu[name][index[found]] * scale
        return values

    faults = np.nan_to_num(from_ecu("faults")).astype(np.int64)
    columns = {
        "time_s": plant["time"][rows], "x": plant["x"][rows], "y": plant["y"][rows],
        "yaw": plant["yaw"][rows], "vx": plant["vx"][rows], "vy": plant["vy"][rows],
        "yaw_rate": plant["yaw_rate"][rows], "steer_angle": plant["steer"][rows],
        "drive_torque": plant["torque"][rows],
        "target_speed": np.array([target_speed(t) for t in plant["time"][rows]]),
        "steer_cmd": from_ecu("steer_angle_cmd"), "torque_cmd": from_ecu("drive_torque_cmd"),
        "lateral_error": errors.lateral_error, "heading_error": errors.heading_error,
        "progress": errors.progress,
        "solver_status": np.nan_to_num(from_ecu("qp_status"), nan=15).astype(np.int64),
        "solver_iterations": np.nan_to_num(from_ecu("qp_iter")).astype(np.int64),
        "solve_time_s": from_ecu("solve_time_us", 1e-6),
        "step_time_s": from_ecu("cycle_time_us", 1e-6),
        "fallback": (faults & 0b0100) != 0, "observer_reset": (faults & 0b1000) != 0,
        "slack_max": np.full(n, np.nan),
    }
    fields = {f.name for f in dataclasses.fields(ClosedLoopTrace)}
    return ClosedLoopTrace(**{name: columns.get(name, np.full(n, np.nan)) for name in fields})


def run_summary(result: Any) -> dict[str, Any]:
    """``hil.session.HilRunResult.summary`` plus what studies/report.py's tables read."""
    from hil.metrics import ComputeTimeStats

    summary = result.summary()
    cycle_s = result.ecu_trace["cycle_time_us"][1:] * 1e-6  # first cycle: one-off set-up
    solve_s = result.ecu_trace["solve_time_us"][1:] * 1e-6
    summary.update(completed=True, failure=None, error=None,
                   compute_time=ComputeTimeStats.of(cycle_s).as_dict() if cycle_s.size else None,
                   solver_time_mean_s=float(np.mean(solve_s)) if solve_s.size else float("nan"))
    return summary


def summary_text(runs: Sequence[dict[str, Any]]) -> str:
    """One screen: a line per run."""
    lines = [f"{'scenario':<12} {'controller':<10} {'max|eY| m':>9} {'RMSE eY':>8} "
             f"{'max|dpsi|':>9} {'RMSE dpsi':>9} {'active':>7} {'ECU ms':>7} {'wall s':>7}"]
    for run in runs:
        head = f"{run['scenario']:<12} {run['controller']:<10}"
        if run.get("error"):
            lines.append(f"{head} FAILED: {run['error']}")
            continue
        lateral = run["tracking"]["lateral_error_m"]
        heading = run["tracking"]["heading_error_rad"]
        median = run["compute_time"]["median_s"] * 1e3 if run.get("compute_time") else float("nan")
        lines.append(f"{head} {lateral['max_abs']:9.3f} {lateral['rmse']:8.3f} "
                     f"{heading['max_abs']:9.3f} {heading['rmse']:9.3f} "
                     f"{run['active_cycles']:>3}/{run['control_cycles']:<3} {median:7.2f} "
                     f"{run['wall_time_s']:7.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the scenarios x controllers over CAN and write the tables, figures and logs."""
    parser = argparse.ArgumentParser(prog="python -m studies.run_all", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--controllers", nargs="+", default=None,
                        help="default: all four; with --ecu c the three the C ECU has (no NMPC)")
    parser.add_argument("--interface", default=None, help="default $CAN_INTERFACE, else virtual")
    parser.add_argument("--channel", default=None, help="default $CAN_CHANNEL, else vcan0")
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--logs", type=Path, default=None, help="default OUT/logs")
    parser.add_argument("--duration", type=float, default=None,
                        help="cut every scenario to this many seconds (quick checks)")
    parser.add_argument("--ecu", choices=("python", "c"), default="python",
                        help="the ECU: python (firmware_sim) or c (build/firmware/ecu, make firmware)")
    args = parser.parse_args(argv)

    from studies.machine_figures import split_machine_keys
    from studies.report import plot_scenario, tracking_table
    from hil.scenario import load_scenario
    from hil.session import C_ECU_CONTROLLERS, RunOptions, reference_path, run_hil

    if args.controllers is None:
        args.controllers = [c for c in CONTROLLERS if args.ecu == "python" or c in C_ECU_CONTROLLERS]

    try:
        scenarios = [load_scenario(name) for name in args.scenarios]
        if args.duration is not None:
            if not args.duration > 0:
                raise HilError(f"--duration must be > 0 s, got {args.duration}")
            scenarios = [dataclasses.replace(s, duration_s=min(s.duration_s, args.duration))
                         for s in scenarios]
        bus = resolve_bus_config(args.interface, args.channel)
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    logs = args.logs or args.out / "logs"
    args.out.mkdir(parents=True, exist_ok=True)
    Path(logs).mkdir(parents=True, exist_ok=True)  # the recorder no longer creates folders

    runs: list[dict[str, Any]] = []
    traces: dict[str, dict[str, Any]] = {}
    jobs = [(s, c) for s in scenarios for c in args.controllers]
    with tqdm(jobs, desc="make run", unit="run") as progress:
        for scenario, controller in progress:
            progress.set_postfix_str(f"{scenario.name} / {controller}")
            # Runs are sequential and close every bus object, so a virtual channel is empty
            # again for the next run; the logs then name the configured channel (vcan0).
            options = RunOptions(controller=controller, bus=bus, lockstep=True,
                                 log_path=logs / f"{scenario.name}__{controller}.log",
                                 ecu_output=logs / f"{scenario.name}__{controller}.ecu.txt",
                                 ecu=args.ecu)
            try:
                result = run_hil(scenario, options)
            except Exception as e:  # noqa: BLE001 - one failed run must not stop the others
                runs.append({"scenario": scenario.name, "controller": controller,
                             "completed": False, "failure": None, "error": f"{e}"})
                continue
            summary = run_summary(result)
            summary["ecu_overruns"] = int(result.ecu_trace["overruns"].max()) \
                if len(result.ecu_trace["overruns"]) else 0
            runs.append(summary)
            traces.setdefault(scenario.name, {})[controller] = report_trace(
                result, reference_path(scenario), scenario.target_speed)

    written = []
    bus_label = bus.describe() + (", C ECU" if args.ecu == "c" else "")
    for scenario in scenarios:
        table, figure, title = _outputs(scenario.name)
        scenario_runs = [r for r in runs if r["scenario"] == scenario.name]
        (args.out / table).write_text(
            tracking_table(f"{title} ({bus_label}, lockstep)", scenario_runs, scenario.name))
        path_xy = scenario.path_points()[:, :2]
        plot_scenario(traces.get(scenario.name, {}), path_xy, f"{title}, {bus_label}",
                      args.out / figure)
        written += [args.out / table, args.out / figure]
    header = {"bus": bus.describe(), "ecu": args.ecu}
    inputs_only, machine = split_machine_keys(runs)
    (args.out / "run_metrics.json").write_text(json.dumps({**header, "runs": inputs_only}, indent=2) + "\n")
    (Path(logs) / "run_timing.json").write_text(json.dumps({**header, "runs": machine}, indent=2) + "\n")
    written += [args.out / "run_metrics.json", Path(logs) / "run_timing.json"]
    print()
    print(summary_text(runs))
    print(f"\nwrote {', '.join(str(p) for p in written)}; frame logs in {logs}/")
    return 0 if all(not r.get("error") for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())

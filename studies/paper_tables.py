"""The double-lane-change study without CAN (``make tables``): every controller on both of
the paper's scenarios, in closed loop with the four-wheel plant (``studies.closed_loop``).

Writes to ``--out`` (default ``results/``):

- ``table2_high_mu.md``, ``table3_low_mu.md``: e_Y and heading error Max / Avg / RMSE per
  controller, the paper's Tables II / III beside them;
- ``fig8_high_mu.png``, ``fig9_low_mu.png``: speed, steer, trajectory, e_Y (Figs 8 / 9);
- ``study_checks.md``: the issue's acceptance checks, PASS / FAIL with the figures;
- ``study_metrics.json``: every number above plus the acceptance checks; the same bytes on
  any machine (``studies.machine_figures.MACHINE_KEYS`` left out);
- ``logs/tables_timing.json`` (not under version control): each run's step and solver
  times and the machine they ran on (``make bench`` compares step times side by side);
- ``traces/<scenario>__<controller>.npz``: the full time series of every run.

Usage: ``python -m studies.paper_tables [--scenarios ...] [--controllers ...] [--no-ablations]
[--out DIR] [--strict]``; by default the paper's four controllers and the two ablations.
Exit status: 0 when every run could be built and run (whatever the checks say; ``--strict``
also requires the checks), 1 otherwise, 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import json
import sys
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from studies.closed_loop import ClosedLoopResult, ClosedLoopTrace, control_steps, run_closed_loop
from hil.errors import HilError
from studies.machine import machine_description
from studies.machine_figures import split_machine_keys
from studies.report import display_name, plot_scenario, tracking_table
from controller.registry import GEOMETRIC_NAMES
from hil.scenario import Scenario, load_scenario

CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
#: Ablations (issue 14 item 6), run by default as extra rows after the four: the observer
#: on LMPC's bicycle (LMPC-ESO) and ESO-DKMPC on a DMDc model with no lift (DMDc-ESO); see
#: docs/controllers.md, "Ablations". ``--no-ablations`` runs the four only.
ABLATIONS = ("lmpc-eso", "dmdc-eso")
#: The geometric baseline (issue 35 item 5), a row after the ablations: what the MPCs buy
#: over a controller with no model (docs/controllers.md, "Stanley").
GEOMETRIC = GEOMETRIC_NAMES
SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
#: Acceptance bound on |e_Y| over every run (m).
MAX_LATERAL_ERROR_M = 2.0
#: The machine's part of the runs (step and solver times, the host), under ``--out``/logs/.
TIMING_FILE = "tables_timing.json"


@dataclass(frozen=True)
class ScenarioOutputs:
    """File names and titles of one scenario's table and figure."""

    table: str
    figure: str
    title: str


OUTPUTS = {
    "dlc_high_mu": ScenarioOutputs("table2_high_mu.md", "fig8_high_mu.png",
                                   "Table II: constant 35 km/h on the high-mu road (mu = 0.85)"),
    "dlc_low_mu": ScenarioOutputs("table3_low_mu.md", "fig9_low_mu.png",
                                  "Table III: varying speed 45-55 km/h on the low-mu road (mu = 0.5)"),
}


def outputs_for(scenario: Scenario) -> ScenarioOutputs:
    return OUTPUTS.get(scenario.name, ScenarioOutputs(
        f"table_{scenario.name}.md", f"fig_{scenario.name}.png", scenario.description))


def run_summary(result: ClosedLoopResult) -> dict[str, Any]:
    """JSON-ready facts and metrics of one run (SI units)."""
    trace = result.trace
    return {
        "scenario": result.scenario,
        "controller": result.controller,
        "completed": result.completed,
        "failure": result.failure,
        "error": None,
        "steps": len(trace),
        "duration_s": float(trace.time_s[-1]) if len(trace) else 0.0,
        "tracking": result.tracking.as_dict(),
        "compute_time": result.compute_time.as_dict(),
        "solver_time_mean_s": float(np.mean(trace.solve_time_s)),
        "steer_limit_held": result.steer_limit_held,
        "max_abs_steer_cmd_rad": float(np.max(np.abs(trace.steer_cmd))),
        "fallback_steps": result.fallback_steps,
        "solver_status_counts": {str(int(k)): int(v) for k, v in
                                 zip(*np.unique(trace.solver_status, return_counts=True))},
        "speed_error_rmse_mps": float(np.sqrt(np.mean((trace.vx - trace.target_speed) ** 2))),
        "final_x_m": float(trace.x[-1]),
    }


def failed_summary(scenario: Scenario, controller: str, error: str) -> dict[str, Any]:
    """Summary of a run that could not even start (controller not buildable)."""
    return {"scenario": scenario.name, "controller": controller, "completed": False,
            "failure": None, "error": error}


def acceptance_checks(runs: Sequence[Mapping[str, Any]], scenarios: Sequence[str],
                      controllers: Sequence[str]) -> list[dict[str, Any]]:
    """The issue's "done when" checks over the study's runs."""
    by_key = {(r["scenario"], r["controller"]): r for r in runs}
    checks = []
    bad = []
    for scenario in scenarios:
        for controller in controllers:
            run = by_key.get((scenario, controller))
            if run is None or run.get("error") or not run["completed"]:
                reason = (run or {}).get("error") or (run or {}).get("failure") or "not run"
                bad.append(f"{controller} on {scenario}: {reason}")
            elif run["tracking"]["lateral_error_m"]["max_abs"] >= MAX_LATERAL_ERROR_M:
                bad.append(f"{controller} on {scenario}: max |e_Y| = "
                           f"{run['tracking']['lateral_error_m']['max_abs']:.3f} m")
    checks.append({"check": f"every controller completes every scenario with |e_Y| < "
                            f"{MAX_LATERAL_ERROR_M} m", "passed": not bad,
                   "detail": "; ".join(bad) or "all runs complete and within bound"})

    def usable(scenario: str, controller: str) -> Mapping[str, Any] | None:
        run = by_key.get((scenario, controller))
        return run if run and not run.get("error") and run["completed"] else None

    if {"eso-dkmpc", "dkmpc"} <= set(controllers):
        for scenario in scenarios:
            eso, dk = usable(scenario, "eso-dkmpc"), usable(scenario, "dkmpc")
            if eso and dk:
                eso_rmse = eso["tracking"]["lateral_error_m"]["rmse"]
                dk_rmse = dk["tracking"]["lateral_error_m"]["rmse"]
                checks.append({"check": f"ESO-DKMPC e_Y RMSE < DKMPC's on {scenario}",
                               "passed": eso_rmse < dk_rmse,
                               "detail": f"{eso_rmse:.4f} m vs {dk_rmse:.4f} m"})
            else:
                checks.append({"check": f"ESO-DKMPC e_Y RMSE < DKMPC's on {scenario}",
                               "passed": False, "detail": "a run is missing or incomplete"})
    # Step time is a machine figure: make bench reports ESO-DKMPC's against LMPC's, side by
    # side in one run, and no committed check depends on this host's load.
    return checks


def checks_markdown(checks: Sequence[Mapping[str, Any]]) -> str:
    """The acceptance checks as a Markdown list: ``- PASS: check (detail)``."""
    return "".join(f"- {'PASS' if c['passed'] else 'FAIL'}: {c['check']} ({c['detail']})\n" for c in checks)


def run_study(scenarios: Sequence[Scenario], controllers: Sequence[str], out: Path,
              *, show_progress: bool = True, debug: bool = False,
              tuning_path: Path | None = None) -> dict[str, Any]:
    """Run every controller on every scenario and write tables, figures, JSON and traces.

    A run whose controller or plant cannot be built is recorded with its ``error`` and
    the study goes on; ``debug`` prints its traceback.

    ``tuning_path``: another tuning file than ``controller/tuning.toml`` (e.g. the one of
    ``studies.unscheduled_tuning``).

    Returns:
        The document written to ``study_metrics.json``.
    """
    from controller.registry import create_controller

    out.mkdir(parents=True, exist_ok=True)
    (out / "traces").mkdir(exist_ok=True)
    runs: list[dict[str, Any]] = []
    traces: dict[str, dict[str, ClosedLoopTrace]] = {s.name: {} for s in scenarios}
    jobs = [(s, c) for s in scenarios for c in controllers]
    outer = tqdm(jobs, desc="study", unit="run", disable=not show_progress)
    for scenario, name in outer:
        outer.set_postfix_str(f"{name} on {scenario.name}")
        try:
            controller = create_controller(name, tuning_path)
            with tqdm(total=control_steps(scenario), desc=f"{name}/{scenario.name}",
                      unit="step", leave=False, disable=not show_progress) as inner:
                result = run_closed_loop(scenario, controller,
                                         on_control_step=lambda _k: inner.update(1))
        except Exception as e:  # noqa: BLE001 - reported per run; the others still run
            # Building the controller or the plant failed (missing artefact, bad parameter
            # file): the run never started. Failures during a run are in the result instead.
            if debug:
                traceback.print_exc()
            runs.append(failed_summary(scenario, name, f"{type(e).__name__}: {e}"))
            continue
        result.save_npz(out / "traces" / f"{scenario.name}__{name}.npz")
        traces[scenario.name][name] = result.trace
        runs.append(run_summary(result))

    machine = machine_description()
    for scenario in scenarios:
        files = outputs_for(scenario)
        scenario_runs = [r for r in runs if r["scenario"] == scenario.name]
        (out / files.table).write_text(
            tracking_table(f"{files.title} ({scenario.name})", scenario_runs, scenario.name))
        plot_scenario(traces[scenario.name], scenario.path_points()[:, :2],
                      f"{scenario.description}: closed loop, four-wheel plant", out / files.figure)
    checks = acceptance_checks(runs, [s.name for s in scenarios], list(controllers))
    (out / "study_checks.md").write_text(checks_markdown(checks))
    inputs_only, timing = split_machine_keys(runs)
    document = {
        "generated_by": "python -m studies.paper_tables",
        "scenarios": {s.name: {"description": s.description, "mu": s.mu,
                               "duration_s": s.duration_s, "source": s.source.name}
                      for s in scenarios},
        "runs": inputs_only,
        "checks": checks,
    }
    (out / "study_metrics.json").write_text(json.dumps(document, indent=2) + "\n")
    # the machine's part beside the traces, not under version control (results/logs/)
    (out / "logs").mkdir(exist_ok=True)
    (out / "logs" / TIMING_FILE).write_text(json.dumps({"machine": machine, "runs": timing}, indent=2) + "\n")
    return {**document, "runs": runs}


def summary_text(document: Mapping[str, Any]) -> str:
    """One screen: a line per run and a line per check."""
    lines = [f"{'scenario':<12} {'controller':<10} {'done':<5} {'max|eY|':>8} {'RMSE eY':>8} "
             f"{'max|dpsi|':>9} {'RMSE dpsi':>9} {'median':>8} {'p99':>8}"]
    for run in document["runs"]:
        head = f"{run['scenario']:<12} {display_name(run['controller']):<10}"
        if run.get("error"):
            lines.append(f"{head} not built: {run['error']}")
            continue
        lateral = run["tracking"]["lateral_error_m"]
        heading = run["tracking"]["heading_error_rad"]
        timing = run["compute_time"]
        lines.append(
            f"{head} {'yes' if run['completed'] else 'NO':<5} {lateral['max_abs']:8.3f} "
            f"{lateral['rmse']:8.3f} {heading['max_abs']:9.3f} {heading['rmse']:9.3f} "
            f"{timing['median_s'] * 1e3:6.2f}ms {timing['p99_s'] * 1e3:6.2f}ms")
        if not run["completed"]:
            lines.append(f"    stopped: {run['failure']}")
    lines.append("")
    for check in document["checks"]:
        lines.append(f"[{'PASS' if check['passed'] else 'FAIL'}] {check['check']}: "
                     f"{check['detail']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.paper_tables", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS),
                        help="scenario names or TOML files (default: %(default)s)")
    parser.add_argument("--controllers", nargs="+", default=list(CONTROLLERS + ABLATIONS + GEOMETRIC),
                        choices=CONTROLLERS + ABLATIONS + GEOMETRIC,
                        help="controllers (default: the paper's four, the ablations and Stanley %(default)s)")
    parser.add_argument("--no-ablations", action="store_true",
                        help=f"leave out the ablations ({', '.join(ABLATIONS)})")
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder")
    parser.add_argument("--strict", action="store_true",
                        help="exit 1 when an acceptance check fails")
    parser.add_argument("--tuning", type=Path, default=None,
                        help="tuning file (default controller/tuning.toml)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bars")
    parser.add_argument("--debug", action="store_true", help="tracebacks on errors")
    args = parser.parse_args(argv)
    if args.tuning is not None and not args.tuning.is_file():
        print(f"error: --tuning {args.tuning}: no such file", file=sys.stderr)
        return 1
    try:
        scenarios = [load_scenario(name) for name in args.scenarios]
        controllers = [c for c in args.controllers if not (args.no_ablations and c in ABLATIONS)]
        document = run_study(scenarios, controllers, args.out,
                             show_progress=not args.no_progress, debug=args.debug, tuning_path=args.tuning)
    except (HilError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(summary_text(document))
    print(f"\nwrote {args.out}/: tables, figures, study_checks.md, study_metrics.json, traces/, "
          f"logs/{TIMING_FILE}")
    not_built = [r for r in document["runs"] if r.get("error")]
    if not_built:
        print(f"error: {len(not_built)} run(s) could not be built", file=sys.stderr)
        return 1
    if args.strict and not all(c["passed"] for c in document["checks"]):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The pose step of the QP MPCs: eq. 20's explicit Euler against the step's midpoint heading
(``make pose-step``).

Every QP MPC predicts its pose over the horizon by eq. 20 (``controller.pose_kinematics``).
Explicit Euler moves each step along the yaw at its start, so on an arc the predicted path
lags the true one by half a step's turn and runs outside it; the MPC steers inside the arc
to make up for it. ``pose_heading_advance`` = 0.5 moves each step along its midpoint
heading instead. This study measures what that changes, with every other field at the
tuning file's value (weights chosen by ``make tune`` with eq. 20):

- the tuning procedure's objective (``studies.tuning_sweep_executor.objective``: the mean
  e_Y RMSE, a run that does not complete counts 10 m) on the tuning set with disturbances
  (``studies.observer_tuning.disturbed_tuning_set``, 22 runs), per QP MPC and setting;
- e_Y RMSE on the lane changes of Tables II / III and the straight-curve-straight path of
  ``make disturbances`` (no disturbance), with NMPC and Stanley, which have no such step,
  beside them; on that path also the mean e_Y on the arc (curvature within 2 % of its
  largest), where the lag shows as a standing offset to the inside (+ = left, the curve's
  inside);
- ``pose_step.png``: e_Y along that path.

A measurement, not a tuning stage: it writes no tuning file. Choosing the pose step by the
procedure means choosing the weights with it too (``make tune``), since the weights were
chosen to work with eq. 20's lag.

Usage: ``python -m studies.pose_step [--out DIR] [--workers N] [--no-progress]``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from controller.registry import create_controller
from controller.tuning import load_tuning
from hil.scenario import Scenario, load_scenario
from studies.closed_loop import ClosedLoopResult, load_reference_path, run_closed_loop
from studies.observer_tuning import disturbed_tuning_set
from studies.tuning_sweep_executor import Evaluation, SweepExecutor, build_controller
from studies.tuning_sweep_grids import Setting, with_setting

#: The controllers with eq. 20's pose step (the QP MPCs).
QP_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "lmpc-eso", "dmdc-eso")
#: Controllers without it, run beside them on the study scenarios for scale.
REFERENCE_CONTROLLERS = ("nmpc", "stanley")
#: The pose step's settings: eq. 20 (explicit Euler) and the midpoint heading.
ADVANCES = (0.0, 0.5)
#: The study scenarios: Tables II / III's lane changes and make disturbances' curve path.
STUDY_SCENARIOS = ("dlc_high_mu", "dlc_low_mu", "straight_curve")
CURVE_SCENARIO = "straight_curve"
#: The arc: where the path's curvature is within this share of its largest.
ARC_TOLERANCE = 0.02
FIGURE_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")


def setting(advance: float) -> Setting:
    """The one-field override of ``pose_heading_advance``."""
    return (("pose_heading_advance", advance),)


def label(advance: float) -> str:
    """The setting's name in tables and legends: "eq. 20 (Euler)" for 0, "midpoint" for 0.5."""
    return "eq. 20 (Euler)" if advance == 0.0 else "midpoint"


def arc_mask(scenario: Scenario, progress: np.ndarray) -> np.ndarray:
    """Samples (by the foot point's arc length ``progress`` (n,)) on the path's arc."""
    path = load_reference_path(scenario)
    s = np.linspace(0.0, path.length, 4001)
    poses = path.pose_at(s)
    curvature = np.abs(np.gradient(np.unwrap(poses[:, 2]), s))
    on_arc = curvature >= (1.0 - ARC_TOLERANCE) * curvature.max()
    return np.interp(progress, s, on_arc.astype(float)) > 0.5


def evaluate(controllers: Sequence[str], scenarios: Sequence[Scenario], tuning: Any, workers: int,
             progress: bool, desc: str) -> list[Evaluation]:
    """Each QP controller at each advance (and the reference controllers as they are) on
    ``scenarios``, in job order."""
    jobs = [(name, "pose-step", setting(advance)) for name in controllers if name in QP_CONTROLLERS
            for advance in ADVANCES]
    jobs += [(name, "reference", ()) for name in controllers if name in REFERENCE_CONTROLLERS]
    bar = tqdm(total=len(jobs) * len(scenarios), desc=desc, unit="run", disable=not progress)
    executor = SweepExecutor(scenarios, tuning, run_closed_loop, workers, bar)
    try:
        return executor.evaluate(jobs)
    finally:
        executor.close()
        bar.close()


def curve_runs(tuning: Any, progress: bool) -> dict[str, ClosedLoopResult]:
    """The curve path's runs with traces (for the arc and the figure): key ``name@advance``."""
    scenario = load_scenario(CURVE_SCENARIO)
    runs = {}
    keys = [(name, advance) for name in FIGURE_CONTROLLERS for advance in ADVANCES] + [("nmpc", None)]
    for name, advance in tqdm(keys, desc="curve traces", unit="run", disable=not progress):
        controller = (create_controller(name) if advance is None
                      else build_controller(name, with_setting(tuning, name, setting(advance))))
        runs[f"{name}@{advance}"] = run_closed_loop(scenario, controller)
    return runs


def _stored(evaluation: Evaluation) -> dict[str, Any]:
    """An evaluation for the JSON, without its wall time (so that a rerun of the same code
    writes the same bytes)."""
    fields = evaluation.as_dict()
    fields.pop("seconds")
    return fields


def _rmse_cell(evaluation: Evaluation, scenario: str, scale: float) -> str:
    if not evaluation.completed[scenario]:
        return "-"
    return f"{scale * evaluation.rmse_m[scenario]:.2f}"


def report(tuning_set: Sequence[Evaluation], studies: Sequence[Evaluation], curve: Mapping[str, ClosedLoopResult],
           scenario_names: Sequence[str]) -> tuple[str, dict[str, Any]]:
    """Markdown and JSON of the study."""
    by_key = {(e.controller, dict(e.setting).get("pose_heading_advance")): e for e in tuning_set}
    lines = ["# The pose step: eq. 20's explicit Euler against the midpoint heading", "",
             "Written by `make pose-step` (`python -m studies.pose_step`; its docstring says what and why). "
             "Closed loop without CAN; every field but `pose_heading_advance` at the tuning file's value "
             "(weights chosen by `make tune` with eq. 20). A measurement: it writes no tuning file.", "",
             f"## The tuning set with disturbances ({len(scenario_names)} runs)", "",
             "The tuning procedure's objective (mean e_Y RMSE, mm; a run that does not complete counts 10 m) "
             "and how many runs each setting has the lower RMSE on.", "",
             "| controller | eq. 20 (Euler) | midpoint | midpoint / Euler | runs lower with the midpoint |",
             "|---|---:|---:|---:|---:|"]
    summary: dict[str, Any] = {"tuning_set": {}, "studies": {}, "arc_offset_cm": {}, "scenarios": list(scenario_names)}
    for name in QP_CONTROLLERS:
        euler, midpoint = by_key.get((name, 0.0)), by_key.get((name, 0.5))
        if euler is None or midpoint is None:
            continue
        lower = sum(midpoint.rmse_m[s] < euler.rmse_m[s] for s in scenario_names
                    if euler.completed[s] and midpoint.completed[s])
        ratio = midpoint.objective_m / euler.objective_m
        lines.append(f"| {name} | {1e3 * euler.objective_m:.2f} | {1e3 * midpoint.objective_m:.2f} | "
                     f"{ratio:.3f} | {lower} of {len(scenario_names)} |")
        summary["tuning_set"][name] = {"euler": _stored(euler), "midpoint": _stored(midpoint),
                                       "objective_ratio": ratio, "runs_lower_with_midpoint": lower}
    lines += ["", "Per run, e_Y RMSE (mm), eq. 20 / midpoint:", "",
              "| run | " + " | ".join(n for n in QP_CONTROLLERS if (n, 0.0) in by_key) + " |",
              "|---|" + "---:|" * sum((n, 0.0) in by_key for n in QP_CONTROLLERS)]
    for s in scenario_names:
        cells = [f"{_rmse_cell(by_key[(n, 0.0)], s, 1e3)} / {_rmse_cell(by_key[(n, 0.5)], s, 1e3)}"
                 for n in QP_CONTROLLERS if (n, 0.0) in by_key]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    study_names = [s for s in STUDY_SCENARIOS if all(s in e.rmse_m for e in studies)]
    lines += ["", "## The study scenarios", "", "e_Y RMSE (cm); NMPC and Stanley have no such step.", "",
              "| controller | setting | " + " | ".join(study_names) + " |", "|---|---|" + "---:|" * len(study_names)]
    for e in studies:
        advance = dict(e.setting).get("pose_heading_advance")
        name_label = "-" if advance is None else label(advance)
        lines.append(f"| {e.controller} | {name_label} | " + " | ".join(_rmse_cell(e, s, 100.0) for s in study_names) + " |")
        summary["studies"][f"{e.controller}@{advance}"] = _stored(e)
    if curve:
        scenario = load_scenario(CURVE_SCENARIO)
        lines += ["", f"Mean e_Y on the arc of `{CURVE_SCENARIO}` (cm, + = the curve's inside):", "",
                  "| controller | eq. 20 (Euler) | midpoint |", "|---|---:|---:|"]
        offsets: dict[str, dict[str, float]] = {}
        for key, result in curve.items():
            name, advance = key.split("@")
            trace = result.trace
            on_arc = arc_mask(scenario, trace.progress)
            offsets.setdefault(name, {})[advance] = float(100.0 * np.mean(trace.lateral_error[on_arc]))
        for name, values in offsets.items():
            if "None" in values:
                lines.append(f"| {name} | {values['None']:+.2f} | (no step) |")
            else:
                lines.append(f"| {name} | {values['0.0']:+.2f} | {values['0.5']:+.2f} |")
        summary["arc_offset_cm"] = offsets
        lines += ["", "![e_Y along the straight-curve-straight path](pose_step.png)"]
    return "\n".join(lines) + "\n", summary


def figure(curve: Mapping[str, ClosedLoopResult], out: Path) -> None:
    """e_Y (cm) along the curve path: each figure controller with both steps, NMPC dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenario = load_scenario(CURVE_SCENARIO)
    fig, axes = plt.subplots(len(FIGURE_CONTROLLERS), 1, figsize=(9, 2.4 * len(FIGURE_CONTROLLERS)), sharex=True)
    nmpc = curve.get("nmpc@None")
    for ax, name in zip(np.atleast_1d(axes), FIGURE_CONTROLLERS):
        for advance, style in zip(ADVANCES, ("-", "-.")):
            trace = curve[f"{name}@{advance}"].trace
            ax.plot(trace.progress, 100.0 * trace.lateral_error, style, label=f"{name}, {label(advance)}")
        if nmpc is not None:
            ax.plot(nmpc.trace.progress, 100.0 * nmpc.trace.lateral_error, "k--", lw=0.8, label="nmpc")
        on_arc = arc_mask(scenario, curve[f"{name}@0.0"].trace.progress)
        progress = curve[f"{name}@0.0"].trace.progress
        if np.any(on_arc):
            ax.axvspan(progress[on_arc].min(), progress[on_arc].max(), color="0.9", zorder=0)
        ax.set_ylabel("e_Y (cm)")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(True, lw=0.3)
    np.atleast_1d(axes)[-1].set_xlabel("arc length (m); the arc shaded")
    fig.suptitle(f"{CURVE_SCENARIO}: e_Y with eq. 20's pose step and the midpoint heading")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.pose_step", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="parallel runs (Ray)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    args.out.mkdir(parents=True, exist_ok=True)
    tuning = load_tuning()
    progress = not args.no_progress
    scenarios = disturbed_tuning_set()
    tuning_set = evaluate(QP_CONTROLLERS, scenarios, tuning, args.workers, progress, "tuning set")
    studies = evaluate(QP_CONTROLLERS + REFERENCE_CONTROLLERS, [load_scenario(s) for s in STUDY_SCENARIOS],
                       tuning, args.workers, progress, "study scenarios")
    curve = curve_runs(tuning, progress)
    text, summary = report(tuning_set, studies, curve, [s.name for s in scenarios])
    (args.out / "pose_step.md").write_text(text)
    (args.out / "pose_step.json").write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
    figure(curve, args.out / "pose_step.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

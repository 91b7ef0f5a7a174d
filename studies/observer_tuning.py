"""The observer stage of the tuning procedure on the tuning set with disturbances added
(``make tune-observer``).

``make tune`` (``studies.tuning_sweep``) chose every controller's weights, and the observer
poles and decay of the controllers with an observer, on the tuning set
(``studies.tuning_set``): eight nominal manoeuvres, no disturbance. An observer exists for
disturbances, so on that set the sweep could only learn that it costs something: it chose
the slowest pole on its grid. This module reruns the sweep's observer stage (stage 2: the
observer fields over a grid, every other field at the tuning file's value) for each
controller with an observer, on the tuning set and three steady drives
(``studies.steady_drives``: long straights around one gentle curve, where a constant
disturbance leaves a standing offset), plus the same ten each with one constant disturbance
(:data:`TUNING_DISTURBANCES`): 22 runs. Sizes and paths differ from those the
disturbance study reports (``make disturbances``): the study's two sizes per disturbance and
its lane change and straight-curve-straight path never enter here.

Objective, runs and failure penalty: the sweep's
(``studies.tuning_sweep_executor.objective``, the mean e_Y RMSE over the 22 runs, a run
that does not complete counts 10 m). The setting with the smallest objective is written
into ``controller/tuning.toml`` (its observer fields only, each table's other fields
untouched) unless ``--no-write``; ``results/observer_tuning.md`` and ``.json`` list every
evaluation.

A refinement, ``--stage refine`` (``make tune-observer-refine``, right after this stage),
runs the same procedure over :data:`REFINE_GRID` for the same controllers, every other
field at the tuning file's value (the ones this stage just chose): the innovation bound's
widening while the innovation keeps its sign (``eso_innovation_persistence``,
``models.eso.PersistentInnovationBound``; 0 keeps the fixed bound) and a finer grid of the
yaw-rate bias pole than this stage's two levels. It writes ``observer_tuning_refine.md``
and ``.json``.

A second stage, ``--stage slip-target`` (``make tune-slip-target``, after the refinement), runs
the same procedure over :data:`SLIP_TARGET_GRID`: the bound and the fade of the heading
target's measured side slip (``controller.steady_slip``), every other field (the observer
fields just chosen included) at the tuning file's value. The target is a part of every
MPC's cost, not of the observer, so this stage tunes every MPC (DKMPC, LMPC and NMPC
too): no baseline keeps the heading cost that the disturbances punish while the observer's
controllers lose it. It writes ``observer_tuning_slip_target.md`` and ``.json``.

Usage: ``python -m studies.observer_tuning [--stage observer|refine|slip-target] [--controllers ...]
[--workers N] [--out DIR] [--no-write] [--no-progress]``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from controller.registry import MPC_NAMES
from controller.tuning import DEFAULT_TUNING_PATH, load_tuning
from hil.errors import HilError
from hil.scenario import Scenario
from studies.closed_loop import run_closed_loop
from studies.steady_drives import steady_scenarios
from studies.tuning_set import tuning_scenarios
from studies.tuning_file import update_tuning_text
from studies.tuning_sweep_executor import Evaluation, SweepExecutor, best
from studies.tuning_sweep_grids import Setting, SweepGrid, setting_text, tuning_table_attribute

#: The controllers with an observer (their tables have the observer fields).
OBSERVED_CONTROLLERS = ("eso-dkmpc", "lmpc-eso", "dmdc-eso")
#: The observer grid: error poles, horizon decay, innovation bound, yaw-rate bias pole.
OBSERVER_GRID = SweepGrid((
    ("eso_pole", (0.0, 0.5)),
    ("eso_second_pole", (0.95, 0.98, 0.995)),
    ("disturbance_decay", (0.8, 1.0)),
    ("eso_innovation_limit", (0.0, 0.003, 0.01)),
    ("yaw_rate_bias_pole", (1.0, 0.99)),
))
#: The refinement after the observer grid: the innovation bound's widening (steps per limit;
#: 0: a fixed bound), the lateral acceleration (m/s^2) below which it widens (0: at any; a
#: steady drive's |vx r| stays well below 0.5 m/s^2 on its straights) and the yaw-rate bias
#: pole on a finer grid (1: no estimate). Without a widening the gate does nothing, so
#: :func:`distinct_settings` keeps only its 0 there.
REFINE_GRID = SweepGrid((
    ("eso_innovation_persistence", (0.0, 10.0, 20.0)),
    ("eso_widening_lateral_accel", (0.0, 0.5, 1.0)),
    ("yaw_rate_bias_pole", (1.0, 0.99, 0.97, 0.95)),
))
#: The second stage: the heading target's measured side slip, bounded (0: off) and faded
#: with the reference's bend. 0.04 rad is about the slip of a 1 kN crosswind at 50 km/h.
SLIP_TARGET_GRID = SweepGrid((
    ("slip_target_limit", (0.0, 0.01, 0.02, 0.04)),
    ("slip_target_gate", (0.003, 0.01)),
))


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of the observer tuning: its grid, report name, make target and the
    controllers it tunes by default."""

    grid: SweepGrid
    report: str
    target: str
    controllers: tuple[str, ...]


STAGES = {
    "observer": Stage(OBSERVER_GRID, "observer_tuning", "tune-observer", OBSERVED_CONTROLLERS),
    "refine": Stage(REFINE_GRID, "observer_tuning_refine", "tune-observer-refine", OBSERVED_CONTROLLERS),
    "slip-target": Stage(SLIP_TARGET_GRID, "observer_tuning_slip_target", "tune-slip-target", MPC_NAMES),
}
#: One constant disturbance per tuning manoeuvre (``[disturbances]`` keys of
#: ``models.disturbance``), acting from the start.
TUNING_DISTURBANCES: dict[str, dict[str, Any]] = {
    "tuning_40kmh_mu085": {"steer_offset_rad": 0.015},
    "tuning_60kmh_mu085": {"crosswind_force_n": 500.0, "crosswind_cp_m": 0.5},
    "tuning_80kmh_mu085": {"bank_angle_rad": 0.04},
    "tuning_40kmh_mu04": {"yaw_rate_bias_rad_s": 0.007},
    "tuning_60kmh_mu04": {"pull_wheel": "FL", "pull_stiffness_scale": 0.6},
    "tuning_80kmh_mu03": {"bank_angle_rad": -0.04},
    "tuning_speedup_mu06": {"steer_offset_rad": -0.015},
    "tuning_slowdown_mu04": {"crosswind_force_n": -500.0, "crosswind_cp_m": 0.5},
    # the steady drives (studies.steady_drives): where a disturbance leaves a standing offset
    "steady_70kmh_mu085": {"crosswind_force_n": 600.0, "crosswind_cp_m": 0.4},
    "steady_40kmh_mu05": {"bank_angle_rad": -0.05},
    # the only other yaw-rate bias run is curvy at mu 0.4, where its offset never shows
    "steady_55kmh_mu07": {"yaw_rate_bias_rad_s": 0.007},
}
#: The comment the written observer fields carry in the tuning file.
TUNING_COMMENT = "chosen by make {target} on the tuning set with disturbances, results/{report}.md"


def disturbed_tuning_set() -> list[Scenario]:
    """The tuning set and the three steady drives (``studies.steady_drives``), then each again
    with its disturbance (named ``<manoeuvre>+disturbed``): 22 scenarios."""
    from models.disturbance import Disturbances

    nominal = tuning_scenarios() + steady_scenarios()
    missing = sorted(set(TUNING_DISTURBANCES) - {s.name for s in nominal})
    if missing:
        raise HilError(f"TUNING_DISTURBANCES names manoeuvres not in the tuning set: {missing}")
    disturbed = [dataclasses.replace(s, name=f"{s.name}+disturbed",
                                     disturbances=Disturbances.from_mapping(TUNING_DISTURBANCES[s.name],
                                                                            f"TUNING_DISTURBANCES[{s.name}]"))
                 for s in nominal]
    return nominal + disturbed


def observer_settings(tuning: Any, name: str, grid: SweepGrid = OBSERVER_GRID) -> list[Setting]:
    """The grid's distinct settings for controller ``name`` (its table must have every grid
    field)."""
    table = getattr(tuning, tuning_table_attribute(tuning, name))
    missing = [field for field, _ in grid.levels if not hasattr(table, field)]
    if missing:
        raise HilError(f"[{name}] has no observer field(s) {missing}")
    return distinct_settings(grid.settings())


def distinct_settings(settings: Sequence[Setting]) -> list[Setting]:
    """``settings`` without those that build the same controller as an earlier one: a
    widening gate (``eso_widening_lateral_accel`` > 0) where the bound does not widen
    (``eso_innovation_persistence`` 0)."""
    kept = []
    for setting in settings:
        fields = dict(setting)
        if fields.get("eso_innovation_persistence") == 0.0 and fields.get("eso_widening_lateral_accel", 0.0) != 0.0:
            continue
        kept.append(setting)
    return kept


def tune(controllers: Sequence[str], scenarios: Sequence[Scenario], tuning: Any, *, workers: int,
         progress: bool = True, grid: SweepGrid = OBSERVER_GRID) -> dict[str, list[Evaluation]]:
    """Every grid setting of each controller on every scenario: controller -> evaluations in
    grid order."""
    jobs = [(name, "observer", setting) for name in controllers for setting in observer_settings(tuning, name, grid)]
    bar = tqdm(total=len(jobs) * len(scenarios), desc="observer tuning", unit="run", disable=not progress)
    executor = SweepExecutor(scenarios, tuning, run_closed_loop, workers, bar)
    try:
        evaluations = executor.evaluate(jobs)
    finally:
        executor.close()
        bar.close()
    out: dict[str, list[Evaluation]] = {name: [] for name in controllers}
    for evaluation in evaluations:
        out[evaluation.controller].append(evaluation)
    return out


def report_markdown(results: Mapping[str, list[Evaluation]], previous: Mapping[str, Setting],
                    scenarios: Sequence[Scenario], *, command: str, seconds: float,
                    grid: SweepGrid = OBSERVER_GRID) -> str:
    """The report: per controller the previous and the chosen observer setting with their
    objectives (nominal half, disturbed half, all), and the five best settings."""
    nominal = [s.name for s in scenarios if not s.name.endswith("+disturbed")]
    disturbed = [s.name for s in scenarios if s.name.endswith("+disturbed")]

    def half(e: Evaluation, names: Sequence[str]) -> str:
        values = [e.rmse_m[n] if e.completed[n] else float("nan") for n in names]
        failed = sum(not e.completed[n] for n in names)
        mean = sum(v for v in values if v == v) / max(1, len(values) - failed)
        return f"{mean:.4f}" + (f" ({failed} failed)" if failed else "")

    lines = ["# Observer tuning on the tuning set with disturbances", "",
             f"Written by `{command}` ({seconds / 60:.1f} min). Each setting runs the {len(nominal)} "
             "manoeuvres of the tuning set and the steady drives (`studies.steady_drives`) and the same "
             f"{len(disturbed)} with one constant disturbance each "
             "(`studies.observer_tuning.TUNING_DISTURBANCES`); the objective is the mean e_Y RMSE (m) "
             f"over the {len(scenarios)} runs, 10 m for a run that does not complete. Every other field of the "
             "controller's table stays as `controller/tuning.toml` has it (weights from `make tune`).", "",
             "Disturbances: " + "; ".join(f"{n}: " + ", ".join(f"{k} {v}" for k, v in d.items())
                                          for n, d in TUNING_DISTURBANCES.items()) + ".", "",
             f"Grid: {', '.join(f'{f} {list(v)}' for f, v in grid.levels)}.", ""]
    for name, evaluations in results.items():
        chosen = best(evaluations)
        before = next((e for e in evaluations if dict(e.setting) == dict(previous[name])), None)
        lines += [f"## {name}", "", f"| setting | objective (m) | nominal {len(nominal)} | disturbed {len(disturbed)} |", "|---|---|---|---|"]
        if before is not None:
            lines.append(f"| before: {setting_text(before.setting)} | {before.objective_m:.4f} | "
                         f"{half(before, nominal)} | {half(before, disturbed)} |")
        else:
            lines.append(f"| before: {setting_text(previous[name])} (not on the grid) | | | |")
        lines.append(f"| **chosen: {setting_text(chosen.setting)}** | {chosen.objective_m:.4f} | "
                     f"{half(chosen, nominal)} | {half(chosen, disturbed)} |")
        ranked = sorted(evaluations, key=lambda e: e.objective_m)[:5]
        lines += ["", "Best five:", "", f"| setting | objective (m) | nominal {len(nominal)} | disturbed {len(disturbed)} |", "|---|---|---|---|"]
        lines += [f"| {setting_text(e.setting)} | {e.objective_m:.4f} | {half(e, nominal)} | {half(e, disturbed)} |"
                  for e in ranked]
        lines.append("")
    return "\n".join(lines)


def _previous(tuning: Any, name: str, grid: SweepGrid) -> Setting:
    table = getattr(tuning, tuning_table_attribute(tuning, name))
    return tuple((field, float(getattr(table, field))) for field, _ in grid.levels)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.observer_tuning", description=__doc__.split("\n\n")[0])
    parser.add_argument("--stage", choices=sorted(STAGES), default="observer",
                        help="observer: the poles, decay, bound and bias (default); slip-target: the heading "
                             "target's side slip, after it")
    parser.add_argument("--controllers", nargs="+", choices=MPC_NAMES,
                        help="controllers to tune (default: the observer stage's, those with an observer; "
                             "the slip-target stage's, every MPC)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="parallel runs (Ray)")
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    parser.add_argument("--tuning", type=Path, default=DEFAULT_TUNING_PATH, help="tuning file read and written")
    parser.add_argument("--no-write", action="store_true", help="do not write the tuning file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if not args.out.is_dir():
        print(f"error: --out {args.out}: no such folder", file=sys.stderr)
        return 1
    stage = STAGES[args.stage]
    controllers = args.controllers or list(stage.controllers)
    started = time.perf_counter()
    try:
        tuning = load_tuning(args.tuning)
        scenarios = disturbed_tuning_set()
        previous = {name: _previous(tuning, name, stage.grid) for name in controllers}
        results = tune(controllers, scenarios, tuning, workers=args.workers, progress=not args.no_progress,
                       grid=stage.grid)
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    seconds = time.perf_counter() - started
    command = f"make {stage.target}"
    (args.out / f"{stage.report}.md").write_text(
        report_markdown(results, previous, scenarios, command=command, seconds=seconds, grid=stage.grid),
        encoding="utf-8")
    document = {"command": command, "seconds": seconds, "grid": {f: list(v) for f, v in stage.grid.levels},
                "disturbances": TUNING_DISTURBANCES,
                "evaluations": [e.as_dict() for evaluations in results.values() for e in evaluations]}
    (args.out / f"{stage.report}.json").write_text(json.dumps(document, indent=1, sort_keys=True) + "\n",
                                                  encoding="utf-8")
    chosen = {name: best(evaluations).setting for name, evaluations in results.items()}
    for name, setting in chosen.items():
        print(f"{name}: {setting_text(setting)} (objective {best(results[name]).objective_m:.4f} m)")
    if not args.no_write:
        text = args.tuning.read_text(encoding="utf-8")
        temporary = args.tuning.with_name(args.tuning.name + ".tmp")
        temporary.write_text(update_tuning_text(text, chosen, comment=TUNING_COMMENT.format(target=stage.target,
                                                                                         report=stage.report)), encoding="utf-8")
        os.replace(temporary, args.tuning)
        print(f"wrote the {args.stage} fields into {args.tuning}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

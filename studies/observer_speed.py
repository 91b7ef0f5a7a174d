"""The observer's speed against model mismatch (``make observer-speed``; issue 35, docs/eso.md).

ESO-DKMPC's slow error pole (``eso_second_pole``: the disturbance estimate's time constant,
about Ts / (1 - pole)) decides how fast the estimate follows a model error. The robustness
grid's mismatch cells (mass +300 kg, steering lag x3) and the tuning set weigh that speed
differently; this study measures both at each pole of the grid's ``tuning`` axis (the
tuning file's own, and the ``[tunings.*]`` tables of ``observer_speed.toml``), every other
field at the tuning file's value:

1. **The robustness grid** (``make robustness``'s cells: double lane change and slalom over
   mu x speed x mass x steering lag), as the campaign grid ``studies/campaign/grids/
   observer_speed.toml``: ESO-DKMPC at each pole (its ``tuning`` axis), DKMPC once. Per pole:
   ESO-DKMPC against DKMPC head to head (``studies.robustness_report.observer_head_to_head``)
   on every cell either completed and on the mismatch cells, and on the nominal cells
   (mass +0 kg, lag x1) that both completed the largest and the mean ratio of their e_Y
   RMSE (the issue's goal on nominal scenarios: at most 1.02).
2. **The tuning procedure's objective** at each pole: the mean e_Y RMSE over the 22 runs of
   ``make tune-observer`` (``studies.observer_tuning.disturbed_tuning_set``: the tuning set
   and the steady drives, each also with a disturbance), the number the procedure chooses
   the observer fields by.

3. **The tuning manoeuvres on changed plants**: would the procedure choose a faster pole if
   its set held model mismatch? The observer stage's 11 runs without a disturbance (the
   tuning set and the steady drives) again on a heavier vehicle and on a slower steering
   (:data:`CHANGED_PLANTS`: +150 kg, lag x2, values the grid never uses), ESO-DKMPC at each
   pole and DKMPC once: the mean e_Y RMSE per plant, over both, and over both together with
   part 2's 22 runs (the objective of a tuning set with the changed plants added).

The grid and the tuning runs are disjoint run sets: the tuning set never drives a lane
change or a slalom, and never the grid's +300 kg or lag x3. Nothing here changes the tuning
file.

Writes ``observer_speed.md``, ``.json`` and ``.png`` to ``--out``. The campaign runs first:
``python -m studies.campaign observer_speed --out DIR`` (``make observer-speed`` does both).

Usage: ``python -m studies.observer_speed --campaign DIR --out DIR [--workers N] [--no-progress]``.
Exit status: 0 written, 1 when it could not be (no campaign, cells missing, a run failed to
build, unwritable output), 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import types
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from hil.errors import HilError
from hil.scenario import Scenario
from studies.campaign.axes import DEFAULT_TUNING
from studies.robustness_records import RunRecord, records_from_rows
from studies.robustness_report import HeadToHead, is_mismatch, observer_head_to_head
from studies.robustness_summary import by_cell
from studies.tuning_sweep_executor import Evaluation, objective

#: The campaign grid of the robustness part.
GRID = "observer_speed"
#: The swept field (its values: the grid's ``[tunings.*]`` tables and the tuning file's).
POLE_FIELD = "eso_second_pole"
CONTROLLER = "eso-dkmpc"
BASELINE = "dkmpc"
#: Part 3's changed plants: name -> (mass offset in kg, steering time constant factor). The
#: grid's mismatch cells use +300 kg and x3; these are milder and disjoint from them.
CHANGED_PLANTS: dict[str, tuple[float, float]] = {"mass+150kg": (150.0, 1.0), "lag_x2": (0.0, 2.0)}


@dataclass(frozen=True)
class PoleRow:
    """One pole's figures: head to head with DKMPC on the grid (every cell either completed,
    the mismatch cells), the nominal cells' e_Y RMSE ratio to DKMPC's (largest, mean; NaN
    without a nominal cell both completed) and the tuning set's objective (m)."""

    pole: float
    tuning: str
    every: HeadToHead
    mismatch: HeadToHead
    nominal_cells: int
    nominal_ratio_max: float
    nominal_ratio_mean: float
    tuning_objective_m: float


def grid_poles(tunings: Mapping[str, Sequence[tuple[str, float]]], file_pole: float) -> dict[str, float]:
    """The grid's tuning axis value -> its pole: ``DEFAULT_TUNING`` the tuning file's, every other the
    value its override gives :data:`POLE_FIELD`. Raises HilError for an override that sets
    anything else."""
    poles = {}
    for name, override in tunings.items():
        fields = dict(override)
        if name != DEFAULT_TUNING and set(fields) != {POLE_FIELD}:
            raise HilError(f"grid {GRID}: tuning {name!r} must set {POLE_FIELD} only, got {sorted(fields)}")
        poles[name] = fields.get(POLE_FIELD, file_pole)
    return poles


def nominal_ratios(records: Sequence[RunRecord]) -> list[float]:
    """ESO-DKMPC's e_Y RMSE over DKMPC's on each nominal cell (mass +0 kg, lag x1) both
    completed, in cell order."""
    ratios = []
    for runs in by_cell(records).values():
        eso, dk = runs.get(CONTROLLER), runs.get(BASELINE)
        if eso is None or dk is None or is_mismatch(eso) or not (eso.completed and dk.completed):
            continue
        ratios.append(eso.e_y_rmse / dk.e_y_rmse)
    return ratios


def pole_rows(rows: Sequence[Mapping[str, Any]], poles: Mapping[str, float],
              objectives: Mapping[float, float]) -> list[PoleRow]:
    """The figures of each pole from the campaign's ``rows`` (each with its ``tuning``; the
    baseline's rows at ``file``) and the tuning set's ``objectives`` (pole -> m), by pole."""
    baseline = [row for row in rows if row["controller"] == BASELINE]
    out = []
    for name, pole in sorted(poles.items(), key=lambda item: item[1]):
        observed = [row for row in rows if row["controller"] == CONTROLLER and row.get("tuning", DEFAULT_TUNING) == name]
        records = records_from_rows([*observed, *baseline], (CONTROLLER, BASELINE))
        counts = observer_head_to_head(records)
        if counts is None:
            raise HilError(f"no {CONTROLLER} / {BASELINE} cell at tuning {name!r} either completed")
        ratios = nominal_ratios(records)
        out.append(PoleRow(pole, name, counts[0], counts[1], len(ratios),
                           max(ratios, default=math.nan),
                           sum(ratios) / len(ratios) if ratios else math.nan, objectives[pole]))
    return out


def tuning_evaluations(poles: Sequence[float], *, workers: int, progress: bool) -> dict[float, Evaluation]:
    """Pole -> ESO-DKMPC's evaluation on the observer stage's 22 runs (its ``objective_m``:
    the tuning procedure's objective, m), every other field at the tuning file's value."""
    from controller.tuning import load_tuning
    from studies.observer_tuning import disturbed_tuning_set, tune
    from studies.tuning_sweep_grids import SweepGrid

    grid = SweepGrid(((POLE_FIELD, tuple(sorted(poles))),))
    evaluations = tune([CONTROLLER], disturbed_tuning_set(), load_tuning(), workers=workers,
                       progress=progress, grid=grid)[CONTROLLER]
    return {dict(e.setting)[POLE_FIELD]: e for e in evaluations}


# ---------------------------------------------------------------------------- changed plants

@dataclass(frozen=True)
class ChangedPlantRow:
    """Part 3's figures of one setting (ESO-DKMPC at ``pole``, or DKMPC with ``pole`` None):
    the mean e_Y RMSE (m) per changed plant, the objective over every changed-plant run, and
    the objective over those and the tuning set's 22 runs (NaN for DKMPC, which the observer
    stage does not tune)."""

    controller: str
    pole: float | None
    per_plant_m: dict[str, float]
    objective_m: float
    with_tuning_set_m: float


def changed_plant_set() -> list[Scenario]:
    """The observer stage's runs without a disturbance (the tuning set and the steady
    drives), each on every plant of :data:`CHANGED_PLANTS` (named ``<manoeuvre>+<plant>``):
    the mass as a scenario's ``mass_offset_kg``, the slower steering as the campaign's lag
    axis gives it (``[faults] vehicle.steer_extra_lag_s``, (factor - 1) x the plant's time
    constant), so that :func:`run_on_changed_plant` builds the plant a grid cell would."""
    from models.vehicle_params import load_vehicle_params
    from studies.steady_drives import steady_scenarios
    from studies.tuning_set import tuning_scenarios

    time_constant = load_vehicle_params().steer_time_constant
    out = []
    for plant, (mass_offset_kg, lag_factor) in CHANGED_PLANTS.items():
        for scenario in tuning_scenarios() + steady_scenarios():
            faults = ({"vehicle": {"steer_extra_lag_s": (lag_factor - 1.0) * time_constant}}
                      if lag_factor != 1.0 else {})
            out.append(replace(
                scenario, name=f"{scenario.name}+{plant}", mass_offset_kg=scenario.mass_offset_kg + mass_offset_kg,
                faults=types.MappingProxyType({**scenario.faults, **faults})))
    return out


def run_on_changed_plant(scenario: Scenario, controller: Any) -> Any:
    """``studies.closed_loop.run_closed_loop`` on the plant a closed-loop campaign cell
    builds for ``scenario`` (its mass, and the steering lag of its ``[faults]`` table)."""
    from studies.campaign.closed_loop_cell import plant_for
    from studies.closed_loop import run_closed_loop

    plant, command_type = plant_for(scenario)
    return run_closed_loop(scenario, controller, plant=plant, command_type=command_type)


def plant_means(evaluation: Evaluation) -> dict[str, float]:
    """Changed plant -> the mean e_Y RMSE (m) of ``evaluation``'s runs on it (the objective's
    failure penalty for a run that did not complete)."""
    out = {}
    for plant in CHANGED_PLANTS:
        names = [name for name in evaluation.rmse_m if name.endswith(f"+{plant}")]
        out[plant] = objective({n: evaluation.rmse_m[n] for n in names}, {n: evaluation.completed[n] for n in names})
    return out


def changed_plant_rows(changed: Sequence[Evaluation], tuning: Mapping[float, Evaluation]) -> list[ChangedPlantRow]:
    """Part 3's rows from the ``changed`` plants' evaluations (ESO-DKMPC's carry the pole in
    their setting, DKMPC's none) and part 2's ``tuning`` evaluations (pole -> evaluation)."""
    rows = []
    for evaluation in changed:
        pole = dict(evaluation.setting).get(POLE_FIELD)
        together = math.nan
        if pole is not None:
            base = tuning[pole]
            together = objective({**base.rmse_m, **evaluation.rmse_m}, {**base.completed, **evaluation.completed})
        rows.append(ChangedPlantRow(evaluation.controller, pole, plant_means(evaluation), evaluation.objective_m,
                                    together))
    return rows


def evaluate_changed_plants(poles: Sequence[float], *, workers: int, progress: bool) -> list[Evaluation]:
    """ESO-DKMPC at each pole and DKMPC once on :func:`changed_plant_set`, every other field
    at the tuning file's value."""
    from tqdm import tqdm

    from controller.tuning import load_tuning
    from studies.tuning_sweep_executor import SweepExecutor

    scenarios = changed_plant_set()
    jobs = [(CONTROLLER, "observer", ((POLE_FIELD, pole),)) for pole in sorted(poles)]
    jobs.append((BASELINE, "observer", ()))
    bar = tqdm(total=len(jobs) * len(scenarios), desc="changed plants", unit="run", disable=not progress)
    executor = SweepExecutor(scenarios, load_tuning(), run_on_changed_plant, workers, bar)
    try:
        return executor.evaluate(jobs)
    finally:
        executor.close()
        bar.close()


def report_markdown(rows: Sequence[PoleRow], file_pole: float, changed: Sequence[ChangedPlantRow], *,
                    command: str, seconds: float) -> str:
    """observer_speed.md: the tables and what they say."""
    best = min(rows, key=lambda r: r.tuning_objective_m)
    most = max(rows, key=lambda r: r.mismatch.wins)
    lines = [
        "# The observer's speed against model mismatch",
        "",
        f"Written by `{command}` in {seconds:.0f} s (`studies/observer_speed.py`). ESO-DKMPC at each "
        f"`{POLE_FIELD}`, every other field at the tuning file's value (its own: {file_pole:g}); DKMPC "
        "(no observer) once. Closed loop without CAN.",
        "",
        "- Grid: `make robustness`'s cells (double lane change and slalom, mu x speed x mass x steering "
        "lag; `studies/campaign/grids/observer_speed.toml`). Head to head: cells where either "
        "completed, a run not completed counting as an infinite RMSE; mismatch cells: mass +300 kg or "
        "steering lag x3.",
        "- Nominal ratio: ESO-DKMPC's e_Y RMSE / DKMPC's on the nominal cells (mass +0 kg, lag x1) both "
        "completed (the issue's goal on nominal runs: at most 1.02).",
        "- Tuning set: the objective `make tune-observer` chooses by (mean e_Y RMSE over its 22 runs, "
        "the tuning set and the steady drives with and without a disturbance; disjoint from the grid).",
        "",
        "| second pole | mismatch cells: ESO-DKMPC lower | every cell: ESO-DKMPC lower | nominal ratio max / mean "
        "| tuning set objective (mm) |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        mark = " (tuning file)" if row.tuning == DEFAULT_TUNING else ""
        lines.append(f"| {row.pole:g}{mark} | {row.mismatch.text()} | {row.every.text()} | "
                     f"{row.nominal_ratio_max:.3f} / {row.nominal_ratio_mean:.3f} ({row.nominal_cells} cells) | "
                     f"{1000 * row.tuning_objective_m:.2f} |")
    lines += [
        "",
        f"- The tuning set's objective is lowest at {best.pole:g} ({1000 * best.tuning_objective_m:.2f} mm); "
        f"the grid's mismatch cells favour ESO-DKMPC most at {most.pole:g} ({most.mismatch.wins} of "
        f"{most.mismatch.cells}; tuning set {1000 * most.tuning_objective_m:.2f} mm), where its e_Y RMSE on the "
        f"nominal cells is {most.nominal_ratio_mean:.3f} x DKMPC's on average and {most.nominal_ratio_max:.3f} x "
        "at most.",
        "- The tuning procedure weighs the tuning set only (settings are chosen on scenarios disjoint from "
        "those a table reports): the grid's figures here inform, they do not choose.",
        "",
    ]
    return "\n".join(lines + changed_plant_markdown(changed))


def changed_plant_markdown(changed: Sequence[ChangedPlantRow]) -> list[str]:
    """Part 3's section of observer_speed.md (no lines without rows)."""
    if not changed:
        return []
    plants = list(CHANGED_PLANTS)
    described = ", ".join(f"{name} (mass {mass:+g} kg, steering time constant x{lag:g})"
                          for name, (mass, lag) in CHANGED_PLANTS.items())
    lines = [
        "## The tuning manoeuvres on changed plants",
        "",
        "The observer stage's 11 runs without a disturbance (the tuning set and the steady drives), each on "
        f"{described}: plants the tuning set does not have, milder than the grid's mismatch cells. Mean e_Y "
        "RMSE (mm); the last column adds these runs to the 22 of the tuning set above, the objective of a "
        "tuning set with the changed plants in it.",
        "",
        "| controller | " + " | ".join(plants) + " | changed plants | with the tuning set |",
        "|---|" + "---|" * (len(plants) + 2),
    ]
    for row in changed:
        name = "DKMPC" if row.pole is None else f"ESO-DKMPC {row.pole:g}"
        together = "-" if math.isnan(row.with_tuning_set_m) else f"{1000 * row.with_tuning_set_m:.2f}"
        lines.append(f"| {name} | " + " | ".join(f"{1000 * row.per_plant_m[p]:.2f}" for p in plants)
                     + f" | {1000 * row.objective_m:.2f} | {together} |")
    observed = [row for row in changed if row.pole is not None]
    chosen = min(observed, key=lambda row: row.with_tuning_set_m)
    alone = min(observed, key=lambda row: row.objective_m)
    lines += [
        "",
        f"- With the changed plants added, the objective is lowest at {chosen.pole:g} "
        f"({1000 * chosen.with_tuning_set_m:.2f} mm); on the changed plants alone at {alone.pole:g} "
        f"({1000 * alone.objective_m:.2f} mm).",
    ]
    baseline = [row for row in changed if row.pole is None]
    if baseline:
        beaten = [f"{row.pole:g}" for row in observed if row.objective_m < baseline[0].objective_m]
        lines.append(f"- DKMPC on the changed plants: {1000 * baseline[0].objective_m:.2f} mm; ESO-DKMPC is lower "
                     f"at {', '.join(beaten) if beaten else 'no pole'}.")
    return lines + [""]


def write_figure(rows: Sequence[PoleRow], changed: Sequence[ChangedPlantRow], file: Path) -> None:
    """observer_speed.png: per pole the mismatch cells ESO-DKMPC wins (share), the tuning
    set's objective and that objective with the changed plants' runs added."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poles = [r.pole for r in rows]
    fig, left = plt.subplots(figsize=(6.4, 3.8))
    left.plot(poles, [r.mismatch.wins / r.mismatch.cells for r in rows], "o-", color="tab:blue")
    left.set_xlabel(f"{POLE_FIELD} (disturbance estimate's pole)")
    left.set_ylabel("mismatch cells ESO-DKMPC < DKMPC (share)", color="tab:blue")
    left.axhline(0.5, color="tab:blue", linestyle=":", linewidth=0.8)
    right = left.twinx()
    right.plot(poles, [1000 * r.tuning_objective_m for r in rows], "s--", color="tab:red", label="tuning set")
    together = sorted((r.pole, r.with_tuning_set_m) for r in changed if r.pole is not None)
    if together:
        right.plot([p for p, _ in together], [1000 * v for _, v in together], "^:", color="tab:orange",
                   label="tuning set + changed plants")
        right.legend(loc="upper center", fontsize="small")
    right.set_ylabel("objective (mm)", color="tab:red")
    left.set_title("ESO-DKMPC: the observer's speed, grid against tuning set")
    fig.tight_layout()
    fig.savefig(file, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point (see the module docstring); returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.observer_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, required=True,
                        help=f"the folder the campaign ran into (python -m studies.campaign {GRID} --out DIR)")
    parser.add_argument("--out", type=Path, required=True, help="folder for observer_speed.{md,json,png}")
    parser.add_argument("--workers", type=int, default=2, help="processes for the tuning set's runs (default 2)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                        help="progress bar of the tuning set's runs (default on)")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    from controller.tuning import load_tuning
    from studies.campaign.grid import load_grid
    from studies.campaign.runner import cached_rows

    started = time.monotonic()
    try:
        grid = load_grid(GRID)
        file_pole = getattr(load_tuning().eso_dkmpc, POLE_FIELD)
        poles = grid_poles({name: grid.tunings.get(name, ()) for name in
                            dict.fromkeys(cell.tuning for cell in grid.cells)}, file_pole)
        if not (args.campaign / "cache").is_dir():
            raise HilError(f"--campaign {args.campaign}: no campaign there (run `python -m studies.campaign "
                           f"{GRID} --out {args.campaign}` first)")
        rows = cached_rows(grid, args.campaign)
        if len(rows) < len(grid.cells):
            raise HilError(f"--campaign {args.campaign}: {len(grid.cells) - len(rows)} of the {len(grid.cells)} "
                           f"cells of {GRID} are not computed for this code (run the campaign first)")
        evaluations = tuning_evaluations(list(poles.values()), workers=args.workers, progress=args.progress)
        table = pole_rows(rows, poles, {pole: e.objective_m for pole, e in evaluations.items()})
        changed = changed_plant_rows(evaluate_changed_plants(list(poles.values()), workers=args.workers,
                                                             progress=args.progress), evaluations)
        command = "python -m studies.observer_speed " + " ".join(sys.argv[1:] if argv is None else argv)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "observer_speed.md").write_text(
            report_markdown(table, file_pole, changed, command=command, seconds=time.monotonic() - started),
            encoding="utf-8")
        (args.out / "observer_speed.json").write_text(json.dumps(
            {"field": POLE_FIELD, "file_pole": file_pole, "rows": [asdict(r) for r in table],
             "changed_plants": {name: {"mass_offset_kg": mass, "lag_factor": lag}
                                for name, (mass, lag) in CHANGED_PLANTS.items()},
             "changed_plant_rows": [asdict(r) for r in changed]}, indent=1) + "\n",
            encoding="utf-8")
        write_figure(table, changed, args.out / "observer_speed.png")
    except (HilError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for row in table:
        print(f"{POLE_FIELD} {row.pole:g}: mismatch {row.mismatch.text()}, nominal ratio max "
              f"{row.nominal_ratio_max:.3f}, tuning set {1000 * row.tuning_objective_m:.2f} mm")
    for plant_row in changed:
        print(f"changed plants, {plant_row.controller} {plant_row.pole}: {1000 * plant_row.objective_m:.2f} mm")
    print(f"wrote {args.out}/observer_speed.md, .json, .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

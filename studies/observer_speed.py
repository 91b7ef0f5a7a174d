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

The two are disjoint run sets: the tuning set never drives a lane change or a slalom, and
never a heavier vehicle or a slower steering. Nothing here changes the tuning file.

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
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from hil.errors import HilError
from studies.campaign.axes import DEFAULT_TUNING
from studies.robustness_records import RunRecord, records_from_rows
from studies.robustness_report import HeadToHead, is_mismatch, observer_head_to_head
from studies.robustness_summary import by_cell

#: The campaign grid of the robustness part.
GRID = "observer_speed"
#: The swept field (its values: the grid's ``[tunings.*]`` tables and the tuning file's).
POLE_FIELD = "eso_second_pole"
CONTROLLER = "eso-dkmpc"
BASELINE = "dkmpc"


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


def tuning_objectives(poles: Sequence[float], *, workers: int, progress: bool) -> dict[float, float]:
    """Pole -> the tuning procedure's objective (m) of ESO-DKMPC on the observer stage's 22
    runs, every other field at the tuning file's value."""
    from controller.tuning import load_tuning
    from studies.observer_tuning import disturbed_tuning_set, tune
    from studies.tuning_sweep_grids import SweepGrid

    grid = SweepGrid(((POLE_FIELD, tuple(sorted(poles))),))
    evaluations = tune([CONTROLLER], disturbed_tuning_set(), load_tuning(), workers=workers,
                       progress=progress, grid=grid)[CONTROLLER]
    return {dict(e.setting)[POLE_FIELD]: e.objective_m for e in evaluations}


def report_markdown(rows: Sequence[PoleRow], file_pole: float, *, command: str, seconds: float) -> str:
    """observer_speed.md: the table and what it says."""
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
    return "\n".join(lines)


def write_figure(rows: Sequence[PoleRow], file: Path) -> None:
    """observer_speed.png: per pole the mismatch cells ESO-DKMPC wins (share) and the tuning
    set's objective."""
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
    right.plot(poles, [1000 * r.tuning_objective_m for r in rows], "s--", color="tab:red")
    right.set_ylabel("tuning set objective (mm)", color="tab:red")
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
        objectives = tuning_objectives(list(poles.values()), workers=args.workers, progress=args.progress)
        table = pole_rows(rows, poles, objectives)
        command = "python -m studies.observer_speed " + " ".join(sys.argv[1:] if argv is None else argv)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "observer_speed.md").write_text(
            report_markdown(table, file_pole, command=command, seconds=time.monotonic() - started), encoding="utf-8")
        (args.out / "observer_speed.json").write_text(json.dumps(
            {"field": POLE_FIELD, "file_pole": file_pole, "rows": [asdict(r) for r in table]}, indent=1) + "\n",
            encoding="utf-8")
        write_figure(table, args.out / "observer_speed.png")
    except (HilError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for row in table:
        print(f"{POLE_FIELD} {row.pole:g}: mismatch {row.mismatch.text()}, nominal ratio max "
              f"{row.nominal_ratio_max:.3f}, tuning set {1000 * row.tuning_objective_m:.2f} mm")
    print(f"wrote {args.out}/observer_speed.md, .json, .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

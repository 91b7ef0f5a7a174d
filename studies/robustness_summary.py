"""The robustness grid's summary, measured from the run records (``make robustness``):
per controller the runs completed, not run, and the e_Y RMSE over the cells that every
controller completed (table (a) of ``robustness.md``), and the pivots by mu x speed.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from studies.robustness_cells import MANOEUVRES, Cell
from studies.robustness_records import RunRecord

@dataclass(frozen=True)
class ControllerSummary:
    """One row of the report's table (a)."""

    controller: str
    runs: int
    completed: int
    completed_by_manoeuvre: dict[str, int]
    not_run: int
    common_rmse_mean: float
    common_rmse_median: float
    lowest_count: int


@dataclass(frozen=True)
class GridSummary:
    """What the report shows, measured from the records."""

    controllers: tuple[str, ...]
    cells: tuple[Cell, ...]
    common_cells: tuple[Cell, ...]
    rows: tuple[ControllerSummary, ...]
    #: (mu, speed_kmh) -> (number of common cells, {controller: mean e_Y RMSE}).
    pivot: dict[tuple[float, float], tuple[int, dict[str, float]]]
    #: (mu, speed_kmh) -> {controller: completed runs}, and the runs per group.
    completed_pivot: dict[tuple[float, float], dict[str, int]]
    runs_per_group: int


def by_cell(records: Sequence[RunRecord]) -> dict[Cell, dict[str, RunRecord]]:
    """Records grouped by cell, then controller."""
    grouped: dict[Cell, dict[str, RunRecord]] = {}
    for record in records:
        grouped.setdefault(record.cell, {})[record.controller] = record
    return grouped


def common_completed_cells(records: Sequence[RunRecord], controllers: Sequence[str]) -> list[Cell]:
    """Cells that every one of ``controllers`` completed, in the records' order."""
    return [cell for cell, runs in by_cell(records).items()
            if all(name in runs and runs[name].completed for name in controllers)]


def summarise(records: Sequence[RunRecord], controllers: Sequence[str]) -> GridSummary:
    """Table (a), the pivots, over ``records`` of ``controllers``."""
    grouped = by_cell(records)
    common = common_completed_cells(records, controllers)
    lowest = {name: 0 for name in controllers}
    for cell in common:
        rmse = {name: grouped[cell][name].e_y_rmse for name in controllers}
        best = min(rmse.values())
        for name, value in rmse.items():
            lowest[name] += value == best
    rows = []
    for name in controllers:
        mine = [r for r in records if r.controller == name]
        values = [grouped[cell][name].e_y_rmse for cell in common]
        rows.append(ControllerSummary(
            controller=name, runs=len(mine), completed=sum(r.completed for r in mine),
            completed_by_manoeuvre={m: sum(r.completed for r in mine if r.manoeuvre == m)
                                    for m in MANOEUVRES},
            not_run=sum(r.not_run for r in mine),
            common_rmse_mean=float(np.mean(values)) if values else float("nan"),
            common_rmse_median=float(np.median(values)) if values else float("nan"),
            lowest_count=lowest[name]))
    groups = sorted({(cell.mu, cell.speed_kmh) for cell in grouped})
    pivot = {}
    completed_pivot = {}
    for group in groups:
        in_group = [cell for cell in common if (cell.mu, cell.speed_kmh) == group]
        pivot[group] = (len(in_group), {
            name: float(np.mean([grouped[cell][name].e_y_rmse for cell in in_group]))
            if in_group else float("nan") for name in controllers})
        completed_pivot[group] = {name: sum(
            runs[name].completed for cell, runs in grouped.items()
            if (cell.mu, cell.speed_kmh) == group and name in runs) for name in controllers}
    per_group = len(grouped) // max(1, len(groups))
    return GridSummary(tuple(controllers), tuple(grouped), tuple(common), tuple(rows), pivot,
                       completed_pivot, per_group)

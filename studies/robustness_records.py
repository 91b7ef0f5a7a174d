"""The robustness grid's runs as records (``make robustness``): one :class:`RunRecord` per
(cell, controller), read from the rows of the campaign that ran the grid
(``studies.campaign`` on ``studies/campaign/grids/robustness_closed_loop.toml``, the
``closed_loop`` runner: ``studies.campaign.closed_loop_cell``), and ``robustness.csv``'s
columns.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from studies.campaign.cell import LEAVE_ROAD_M
from studies.robustness_cells import MANOEUVRE_OF_SCENARIO, MANOEUVRES, Cell

ROOT = Path(__file__).resolve().parent.parent

#: One row of ``robustness.csv`` per run, in this order.
CSV_FIELDS = ("controller", "manoeuvre", "mu", "speed_kmh", "mass_offset_kg", "lag_factor",
              "completed", "e_y_rmse", "e_y_max", "heading_rmse", "error")


@dataclass(frozen=True)
class RunRecord:
    """The outcome of one (cell, controller) run.

    ``e_y_rmse`` / ``e_y_max`` (m) and ``heading_rmse`` (rad) are those of the trace as far
    as it went (NaN when the run never started); ``completed`` is False for a run that left
    the road or was stopped, with the reason in ``error``. ``seconds`` is the run's wall time
    in its worker (build included), ``steps`` its control steps.
    """

    controller: str
    manoeuvre: str
    mu: float
    speed_kmh: float
    mass_offset_kg: float
    lag_factor: float
    completed: bool
    e_y_rmse: float
    e_y_max: float
    heading_rmse: float
    error: str
    seconds: float = 0.0
    steps: int = 0
    key: str = ""

    @property
    def cell(self) -> Cell:
        return Cell(self.manoeuvre, self.mu, self.speed_kmh, self.mass_offset_kg, self.lag_factor)

    @property
    def not_run(self) -> bool:
        """True when the controller or the plant could not even be built (no trace)."""
        return not self.completed and self.steps == 0

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "RunRecord":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})

    def csv_row(self) -> dict[str, str]:
        """The :data:`CSV_FIELDS` as text (metrics with 6 decimals, empty when NaN)."""
        row = {name: getattr(self, name) for name in CSV_FIELDS}
        for name in ("e_y_rmse", "e_y_max", "heading_rmse"):
            row[name] = "" if not math.isfinite(row[name]) else f"{row[name]:.6f}"
        row["completed"] = "1" if self.completed else "0"
        for name in ("mu", "speed_kmh", "mass_offset_kg", "lag_factor"):
            row[name] = f"{row[name]:g}"
        return row


def error_text(row: Mapping[str, Any]) -> str:
    """Why a run did not complete, as robustness.csv says it ("" when it did)."""
    if row.get("completed"):
        return ""
    if row.get("error"):
        return str(row["error"])  # could not be built, or its worker died
    if row.get("failure"):
        return f"stopped: {row['failure']}"
    return f"left the road: max |e_Y| = {float(row['e_y_max']):.2f} m > {LEAVE_ROAD_M} m"


def record_from_row(row: Mapping[str, Any]) -> RunRecord:
    """The record of one campaign row (its axes as the campaign wrote them)."""
    nan = float("nan")

    def number(name: str) -> float:
        value = row.get(name)
        return nan if value is None or value == "" else float(value)

    return RunRecord(controller=row["controller"], manoeuvre=MANOEUVRE_OF_SCENARIO[row["scenario"]],
                     mu=float(row["mu"]), speed_kmh=float(row["speed"]),
                     mass_offset_kg=float(row["mass_offset_kg"]), lag_factor=float(row["lag_factor"]),
                     completed=bool(row.get("completed")), e_y_rmse=number("e_y_rmse"),
                     e_y_max=number("e_y_max"), heading_rmse=number("heading_rmse"),
                     error=error_text(row), seconds=float(row.get("wall_s") or 0.0),
                     steps=int(row.get("steps") or 0), key=str(row.get("key", "")))


def records_from_rows(rows: Sequence[Mapping[str, Any]], controllers: Sequence[str]) -> list[RunRecord]:
    """The records of ``rows`` (the controllers ``controllers`` only), cell-major: by
    manoeuvre, mu, speed, mass, lag, then in the order of ``controllers``."""
    order = {name: i for i, name in enumerate(controllers)}
    manoeuvres = list(MANOEUVRES)
    records = [record_from_row(row) for row in rows if row["controller"] in order]
    return sorted(records, key=lambda r: (manoeuvres.index(r.manoeuvre), r.mu, r.speed_kmh,
                                          r.mass_offset_kg, r.lag_factor, order[r.controller]))

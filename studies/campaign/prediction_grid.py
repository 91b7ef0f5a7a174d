"""Grid files of the ``prediction`` runner (Table I, ``make table1``): each cell is one model
row x one seed, its model trained or fitted on the data set and its open-loop prediction
errors measured on the seed's held-out test runs (``studies.campaign.prediction_cell``).

A grid file (``studies/campaign/grids/table1.toml``)::

    name = "table1"
    description = "..."

    [axes]
    runner = "prediction"        # stands alone: these cells are no closed-loop runs
    row = ["DK scheduled, d=5", "DMDc"]     # names of [rows.NAME] tables (default: all, in
                                            # the file's order)
    seed = [0, 1, 2, 3, 4]       # the training's seed: weights and split by run

    [run]
    data = "data/wide"           # the data set (relative to the repository root)

    [rows."DK scheduled, d=5"]
    fit = "train"                # train (default), edmdc-linear, edmdc-bilinear, dmdc,
                                 # edmdc, bicycle, single_track (prediction_rows.FITS)
    states = ["vx", "vy", "yaw_rate"]   # the model's states (default: the data's four)
    settings = { n_features = 5 }       # TrainingSettings overrides (train, edmdc-*)

Cells are the product row x seed, in row order, then seed order (the order of Table I's
rows). Every error is a ``GridError`` naming the file and the key, raised before any cell
runs.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from studies.campaign.axes import PREDICTION_RUNNER, GridError
from studies.campaign.prediction_rows import FITS, TRAIN_FIT, VEHICLE_STATES, WHEEL_STATES, Row

_TOP_KEYS = {"name", "description", "axes", "run", "rows"}
_AXES = ("runner", "row", "seed")
_ROW_KEYS = {"fit", "states", "settings"}
#: The fits that take TrainingSettings overrides.
_SETTINGS_FITS = tuple(fit for fit in FITS if fit == TRAIN_FIT or fit.startswith("edmdc-"))


@dataclass(frozen=True)
class PredictionCell:
    """One cell: a row of the grid (its name) and a seed."""

    row: str
    seed: int
    runner: str = PREDICTION_RUNNER
    #: No prediction cell has to run alone (the runner asks every cell).
    exclusive: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"runner": self.runner, "row": self.row, "seed": self.seed}

    @property
    def label(self) -> str:
        return f"row={self.row}, seed={self.seed}"


@dataclass(frozen=True)
class PredictionGrid:
    """A loaded ``prediction`` grid: the rows by name (file order), the cells, the data set."""

    name: str
    description: str
    source: Path
    rows: Mapping[str, Row]
    cells: tuple[PredictionCell, ...]
    data_dir: Path
    #: The runner of every cell (``studies.campaign.runner`` tells the grids apart by it).
    runner: str = PREDICTION_RUNNER

    def with_rows(self, rows: Sequence[Row], seeds: Sequence[int], data_dir: Path | None = None) -> PredictionGrid:
        """This grid with ``rows`` (in that order) x ``seeds`` as its cells, on ``data_dir``
        (None: the grid's data set)."""
        return dataclasses.replace(self, rows={row.label: row for row in rows},
                                   cells=tuple(PredictionCell(row.label, seed) for row in rows for seed in seeds),
                                   data_dir=self.data_dir if data_dir is None else Path(data_dir))


def load_prediction_grid(file: Path, raw: Mapping[str, Any], root: Path) -> PredictionGrid:
    """Check and expand a ``prediction`` grid's document ``raw`` (read from ``file``).

    Raises:
        GridError: naming the file and the key (module docstring for the schema).
    """
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise GridError(f"{file}: unknown key(s) {', '.join(unknown)} with runner {PREDICTION_RUNNER!r}; "
                        f"known: {', '.join(sorted(_TOP_KEYS))}")
    axes = raw["axes"]
    other = [name for name in axes if name not in _AXES]
    if other:
        raise GridError(f"{file}: axes.{other[0]} with runner {PREDICTION_RUNNER!r}: its axes are "
                        f"{', '.join(_AXES)}")
    if axes["runner"] not in (PREDICTION_RUNNER, [PREDICTION_RUNNER]):
        raise GridError(f"{file}: axes.runner: {PREDICTION_RUNNER!r} stands alone (its cells are model "
                        "rows x seeds, not closed-loop runs)")
    tables = raw.get("rows")
    if not isinstance(tables, dict) or not tables or not all(isinstance(v, dict) for v in tables.values()):
        raise GridError(f"{file}: [rows.NAME] tables are required with runner {PREDICTION_RUNNER!r}")
    rows = {name: _row(file, name, table) for name, table in tables.items()}
    names = _list(file, "row", axes.get("row", list(rows)))
    for name in names:
        if not isinstance(name, str) or name not in rows:
            raise GridError(f"{file}: axes.row value {name!r}: not a [rows.NAME] table of the file "
                            f"({', '.join(map(repr, rows))})")
    seeds = _list(file, "seed", axes.get("seed", [0]))
    for seed in seeds:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise GridError(f"{file}: axes.seed value {seed!r}: must be an integer >= 0")
    run = raw.get("run", {})
    if not isinstance(run, dict) or set(run) - {"data"}:
        raise GridError(f"{file}: [run] takes only data with runner {PREDICTION_RUNNER!r}")
    data = run.get("data", "data/wide")
    if not isinstance(data, str) or not data:
        raise GridError(f"{file}: run.data = {data!r}: must be a path (relative to the repository root)")
    cells = tuple(PredictionCell(name, seed) for name in names for seed in seeds)
    return PredictionGrid(name=str(raw.get("name", file.stem)), description=str(raw.get("description", "")),
                          source=file.resolve(), rows={name: rows[name] for name in names}, cells=cells,
                          data_dir=root / data)


def _list(file: Path, axis: str, raw: Any) -> list[Any]:
    values = raw if isinstance(raw, list) else [raw]
    if not values:
        raise GridError(f"{file}: axes.{axis} is empty")
    if len({repr(v) for v in values}) != len(values):
        raise GridError(f"{file}: axes.{axis} = {values!r}: repeated value")
    return values


def _row(file: Path, name: str, table: Mapping[str, Any]) -> Row:
    from models.errors import ModelError
    from models.koopman_settings import TrainingSettings

    where = f"{file}: rows.{name}"
    unknown = sorted(set(table) - _ROW_KEYS)
    if unknown:
        raise GridError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(_ROW_KEYS))}")
    fit = table.get("fit", TRAIN_FIT)
    if fit not in FITS:
        raise GridError(f"{where}.fit = {fit!r}: choose from {', '.join(FITS)}")
    states = tuple(table.get("states", WHEEL_STATES))
    if not 3 <= len(states) <= len(WHEEL_STATES) or states != WHEEL_STATES[:len(states)]:
        raise GridError(f"{where}.states = {list(states)!r}: must be {list(VEHICLE_STATES)!r} or "
                        f"{list(WHEEL_STATES)!r} (the data's leading states)")
    settings = table.get("settings", {})
    if not isinstance(settings, dict):
        raise GridError(f"{where}.settings: must be a table of TrainingSettings fields")
    if settings and fit not in _SETTINGS_FITS:
        raise GridError(f"{where}.settings: fit {fit!r} takes no training settings ({', '.join(_SETTINGS_FITS)} do)")
    fields = {f.name for f in dataclasses.fields(TrainingSettings)} - {"seed"}
    bad = sorted(set(settings) - fields)
    if bad:
        raise GridError(f"{where}.settings.{bad[0]}: not a TrainingSettings field (the seed is the seed axis)")
    overrides = {key: _tuples(value) for key, value in settings.items()}
    try:
        TrainingSettings(**overrides)
    except (TypeError, ValueError, ModelError) as e:
        raise GridError(f"{where}.settings: {e}") from e
    return Row(name, overrides, states, fit)


def _tuples(value: Any) -> Any:
    """TOML arrays as the tuples ``TrainingSettings`` holds (``hidden``, ``dictionary``)."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value

"""Data recorded elsewhere: named-column CSV files with a small TOML mapping (issue 20).

A simulator's export or a data logger's table, one file per drive, becomes training and
evaluation data for ``python -m models.koopman_train --logs FILE.csv --mapping MAP.toml``.
Such a CSV is told apart from a python-can CSV log by its header
(``models.can_log_data.is_python_can_csv``). The mapping::

    sample_time_s = 0.025          # the model's Ts: the data are resampled to it
    time_column = "t"              # seconds; or file_sample_time_s = 0.01 (rows equally spaced)
    time_scale = 1.0               # optional: 0.001 for a time column in ms

    [states]                       # model name = column, or a table with a scale and offset
    vx = "speed_x"
    vy = { column = "speed_y_kmh", scale = 0.2777778 }
    yaw_rate = "yaw_rate"

    [inputs]
    throttle = "throttle"
    brake = { column = "brake_pct", scale = 0.01 }

Physical value = column * scale + offset. States are interpolated onto the grid, inputs
held (zero-order hold). Rows more than 2.5 median steps apart split a file into segments.
A model whose inputs are not the ECU's [torque, steer] (or whose states the bus does not
carry) is for study: training and prediction errors work, the ECU refuses it
(``controller.registry.check_ecu_model_names``).
"""
from __future__ import annotations

import csv
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.can_log_data import MIN_SEGMENT_S, PIECE_S, LogDataError, pieces
from models.koopman_metrics import Trajectory

GAP_FACTOR = 2.5


@dataclass(frozen=True)
class ColumnMap:
    """One model variable: its column, scale and offset."""

    name: str
    column: str
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class CsvMapping:
    """A parsed mapping file (see the module docstring)."""

    sample_time_s: float
    states: tuple[ColumnMap, ...]
    inputs: tuple[ColumnMap, ...]
    time_column: str | None = None
    file_sample_time_s: float | None = None
    time_scale: float = 1.0


def _number(path: Path, field: str, value: Any) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise LogDataError(f"{path}: field {field} must be a number, got {value!r}")
    return float(value)


def _columns(path: Path, table: Any, section: str) -> tuple[ColumnMap, ...]:
    if not isinstance(table, dict) or not table:
        raise LogDataError(f"{path}: table [{section}] missing or empty (model name = column name)")
    maps = []
    for name, spec in table.items():
        where = f"[{section}] {name}"
        if isinstance(spec, str):
            maps.append(ColumnMap(name, spec))
            continue
        if not isinstance(spec, dict) or not isinstance(spec.get("column"), str):
            raise LogDataError(f"{path}: {where}: expected a column name or {{ column = ..., scale = ... }}")
        unknown = sorted(set(spec) - {"column", "scale", "offset"})
        if unknown:
            raise LogDataError(f"{path}: {where}: unknown field(s) {', '.join(unknown)}")
        maps.append(ColumnMap(name, spec["column"], _number(path, f"{where}.scale", spec.get("scale", 1.0)),
                              _number(path, f"{where}.offset", spec.get("offset", 0.0))))
    return tuple(maps)


def load_mapping(path: str | Path) -> CsvMapping:
    """Parse and check a mapping TOML. Raises LogDataError naming the file and field."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as error:
        raise LogDataError(f"{path}: cannot read the mapping: {error}") from error
    except tomllib.TOMLDecodeError as error:
        raise LogDataError(f"{path}: not valid TOML: {error}") from error
    unknown = sorted(set(raw) - {"sample_time_s", "time_column", "file_sample_time_s", "time_scale",
                                 "states", "inputs"})
    if unknown:
        raise LogDataError(f"{path}: unknown field(s) {', '.join(unknown)}")
    if "sample_time_s" not in raw:
        raise LogDataError(f"{path}: field sample_time_s missing (the model's Ts, e.g. 0.025)")
    ts = _number(path, "sample_time_s", raw["sample_time_s"])
    time_column = raw.get("time_column")
    file_ts = raw.get("file_sample_time_s")
    if (time_column is None) == (file_ts is None):
        raise LogDataError(f"{path}: give exactly one of time_column and file_sample_time_s")
    if time_column is not None and not isinstance(time_column, str):
        raise LogDataError(f"{path}: field time_column must be a column name, got {time_column!r}")
    mapping = CsvMapping(ts, _columns(path, raw.get("states"), "states"), _columns(path, raw.get("inputs"), "inputs"),
                         time_column, None if file_ts is None else _number(path, "file_sample_time_s", file_ts),
                         _number(path, "time_scale", raw.get("time_scale", 1.0)))
    for field, value in (("sample_time_s", mapping.sample_time_s), ("file_sample_time_s", mapping.file_sample_time_s),
                         ("time_scale", mapping.time_scale)):
        if value is not None and not value > 0:
            raise LogDataError(f"{path}: field {field} must be > 0, got {value}")
    return mapping


def _read_table(path: Path, columns: Sequence[str]) -> dict[str, np.ndarray]:
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.reader(handle)
            header = [name.strip() for name in next(reader, [])]
            rows = [row for row in reader if row and any(cell.strip() for cell in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise LogDataError(f"{path}: cannot read the CSV: {error}") from error
    missing = [c for c in columns if c not in header]
    if missing:
        raise LogDataError(f"{path}: column(s) {', '.join(missing)} of the mapping missing "
                           f"(header: {','.join(header)[:200]})")
    table = {}
    for column in columns:
        index = header.index(column)
        values = np.empty(len(rows))
        for number, row in enumerate(rows, start=2):
            try:
                values[number - 2] = float(row[index])
            except (ValueError, IndexError):
                raise LogDataError(f"{path}: line {number}: column {column!r} is not a number") from None
        if not np.all(np.isfinite(values)):
            bad = int(np.flatnonzero(~np.isfinite(values))[0]) + 2
            raise LogDataError(f"{path}: line {bad}: column {column!r} is not finite")
        table[column] = values
    return table


def load_named_csv(files: Sequence[str | Path], mapping: CsvMapping,
                   piece_s: float = PIECE_S) -> list[Trajectory]:
    """Trajectories at ``mapping.sample_time_s`` from named-column CSV files."""
    ts = mapping.sample_time_s
    state_names = tuple(m.name for m in mapping.states)
    input_names = tuple(m.name for m in mapping.inputs)
    runs: list[Trajectory] = []
    for file in files:
        path = Path(file)
        if not path.is_file():
            raise LogDataError(f"{path}: data file not found")
        columns = [m.column for m in (*mapping.states, *mapping.inputs)]
        table = _read_table(path, columns + ([mapping.time_column] if mapping.time_column else []))
        n_rows = len(table[columns[0]])
        if mapping.time_column:
            time = table[mapping.time_column] * mapping.time_scale
        else:
            time = np.arange(n_rows) * float(mapping.file_sample_time_s)
        steps = np.diff(time)
        if n_rows < 2 or np.any(steps <= 0):
            raise LogDataError(f"{path}: time must increase strictly over at least 2 rows")
        physical = {m.name: table[m.column] * m.scale + m.offset for m in (*mapping.states, *mapping.inputs)}
        breaks = np.flatnonzero(steps > GAP_FACTOR * np.median(steps)) + 1
        found = 0
        for start, stop in zip([0, *breaks], [*breaks, n_rows]):
            t = time[start:stop]
            if t[-1] - t[0] < MIN_SEGMENT_S:
                continue
            grid = t[0] + ts * np.arange(int(math.floor((t[-1] - t[0]) / ts + 1e-9)) + 1)
            held = np.clip(np.searchsorted(t, grid + 1e-9, side="right") - 1, 0, len(t) - 1)
            states = np.column_stack([np.interp(grid, t, physical[n][start:stop]) for n in state_names])
            inputs = np.column_stack([physical[n][start:stop][held] for n in input_names])
            for piece_states, piece_inputs in pieces(states, inputs, max(1, round(piece_s / ts))):
                runs.append(Trajectory(f"{path.name}#{found:03d}", piece_states, piece_inputs,
                                       state_names, input_names))
                found += 1
        if not found:
            raise LogDataError(f"{path}: no stretch of at least {MIN_SEGMENT_S} s without gaps")
    return runs

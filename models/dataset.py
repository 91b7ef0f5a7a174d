"""Runs of vehicle data as named columns, and the loader of CSV data sets.

A data set is a directory of CSV files, one run each, with a header of column names
(at least ``RUN_COLUMNS``) and one row per sample. Units SI; ``yaw`` is continuous
(not wrapped) in files this project writes; ``torque`` and ``steer`` are the commands
applied from that sample to the next (zero-order hold), i.e. the model input u.

``load_dataset`` reads every ``*.csv`` of a directory in name order, checks it and
resamples it to ``ts``: states linearly (yaw unwrapped first), inputs as a zero-order
hold, because a command is a step signal (``torque`` and ``steer`` by default; a data set
of other inputs, as a throttle and a brake, names them in ``held``). Malformed files raise
``DatasetError`` naming the file and the column.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from models.errors import DatasetError

RUN_COLUMNS: tuple[str, ...] = ("time", "vx", "vy", "yaw_rate", "x", "y", "yaw", "torque", "steer")
#: Columns that are commands (held between samples) rather than sampled states.
INPUT_COLUMNS: tuple[str, ...] = ("torque", "steer")
#: Sample time of the controller and of the Koopman model (s).
DEFAULT_TS = 0.025
#: Default data set directory (git-ignored), written by ``make data``.
DEFAULT_DATASET_DIR = Path(__file__).resolve().parents[1] / "data" / "nominal"
#: A time step larger than this multiple of the file's median step is a gap.
GAP_FACTOR = 2.0


@dataclass(frozen=True)
class Run:
    """One run: ``columns`` maps a column name to a 1-D array, all of one length n."""

    name: str
    columns: dict[str, np.ndarray]

    @property
    def time(self) -> np.ndarray:
        """Sample times (s), shape (n,)."""
        return self.columns["time"]

    def __len__(self) -> int:
        return len(self.columns["time"])

    def array(self, names: Sequence[str]) -> np.ndarray:
        """Columns ``names`` stacked side by side, shape (n, len(names))."""
        missing = [name for name in names if name not in self.columns]
        if missing:
            raise DatasetError(f"{self.name}: column {missing[0]!r} not in run "
                               f"(has {', '.join(self.columns)})")
        return np.column_stack([self.columns[name] for name in names])


def write_run_csv(path: Path, run: Run, precision: int = 9) -> None:
    """Write ``run`` as CSV with a header (column order of ``run.columns``)."""
    names = list(run.columns)
    table = run.array(names)
    with open(path, "w", newline="") as handle:
        handle.write(",".join(names) + "\n")
        np.savetxt(handle, table, delimiter=",", fmt=f"%.{precision}g")


def read_run_csv(path: Path, columns: Iterable[str] = RUN_COLUMNS) -> Run:
    """Read one CSV run as it is (no resampling), checking ``columns`` are present,
    numeric and finite and that time is strictly increasing. Raises ``DatasetError``."""
    path = Path(path)
    wanted = list(columns)
    if "time" not in wanted:
        wanted = ["time", *wanted]
    try:
        with open(path, newline="") as handle:
            reader = csv.reader(handle)
            header = [name.strip() for name in next(reader, [])]
            rows = [row for row in reader if row]
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc}") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{path}: not a CSV text file: {exc}") from exc
    for name in wanted:
        if name not in header:
            raise DatasetError(f"{path}: column {name!r} missing (header: {','.join(header)})")
    if len(rows) < 2:
        raise DatasetError(f"{path}: column 'time': needs at least 2 rows, got {len(rows)}")
    data: dict[str, np.ndarray] = {}
    for name in wanted:
        index = header.index(name)
        values = np.empty(len(rows))
        for row_number, row in enumerate(rows):
            try:
                values[row_number] = float(row[index])
            except (ValueError, IndexError):
                cell = row[index] if index < len(row) else "<missing>"
                raise DatasetError(f"{path}: column {name!r}: row {row_number + 1}: "
                                   f"not a number: {cell!r}") from None
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise DatasetError(f"{path}: column {name!r}: NaN or infinite value in row "
                               f"{bad[0] + 1} ({bad.size} row(s) in all)")
        data[name] = values
    steps = np.diff(data["time"])
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        raise DatasetError(f"{path}: column 'time': not strictly increasing at row {bad[0] + 2} "
                           f"({float(data['time'][bad[0]])!r} -> {float(data['time'][bad[0] + 1])!r})")
    median = float(np.median(steps))
    gaps = np.flatnonzero(steps > GAP_FACTOR * median)
    if gaps.size:
        g = gaps[0]
        raise DatasetError(f"{path}: column 'time': gap of {steps[g]:.6g} s after row {g + 1} "
                           f"(t = {data['time'][g]:.6g} s; median step {median:.6g} s)")
    return Run(name=path.stem, columns=data)


def resample(run: Run, ts: float = DEFAULT_TS, held: Sequence[str] = INPUT_COLUMNS) -> Run:
    """``run`` on the grid t0 + k ts within its time span.

    States are interpolated linearly (``yaw`` unwrapped first, so it stays continuous);
    the columns ``held`` (the inputs, ``INPUT_COLUMNS`` by default) are held (zero-order
    hold), since a command is constant between samples. A run already on the grid is
    returned with unchanged values.
    """
    if not (math.isfinite(ts) and ts > 0.0):
        raise DatasetError(f"{run.name}: ts must be > 0, got {ts!r}")
    time = run.time
    count = int(math.floor((time[-1] - time[0]) / ts + 1e-6)) + 1
    grid = time[0] + ts * np.arange(count)
    out: dict[str, np.ndarray] = {"time": grid}
    # Index of the last sample at or before each grid time (tolerant to rounding).
    held_index = np.clip(np.searchsorted(time, grid + 1e-9 * ts, side="right") - 1, 0, len(time) - 1)
    for name, values in run.columns.items():
        if name == "time":
            continue
        if name in held:
            out[name] = values[held_index]
        else:
            source = np.unwrap(values) if name == "yaw" else values
            out[name] = np.interp(grid, time, source)
    return Run(name=run.name, columns=out)


def load_dataset(directory: str | Path = DEFAULT_DATASET_DIR, ts: float = DEFAULT_TS,
                 columns: Sequence[str] = RUN_COLUMNS, held: Sequence[str] = INPUT_COLUMNS) -> list[Run]:
    """Every ``*.csv`` run in ``directory`` (name order), checked and resampled to ``ts``
    (the columns ``held`` as a zero-order hold, see ``resample``).

    Raises ``DatasetError`` for a missing directory, no CSV files, or a malformed file
    (missing column, non-numeric or NaN value, non-monotonic time, gap).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetError(f"{directory}: data set directory not found (run `make data`?)")
    files = sorted(directory.glob("*.csv"))
    if not files:
        raise DatasetError(f"{directory}: no *.csv runs in the data set directory")
    return [resample(read_run_csv(path, columns), ts, held) for path in files]

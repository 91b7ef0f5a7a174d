"""Loader of external data sets: checks, clear errors, resampling to Ts."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.dataset import RUN_COLUMNS, Run, load_dataset, read_run_csv, resample, write_run_csv
from models.errors import DatasetError


def _write(path: Path, header: str, rows: list[list[float | str]]) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in row) for row in rows) + "\n")
    return path


def _good_rows(n: int = 20, dt: float = 0.01) -> list[list[float]]:
    return [[k * dt, 10.0 + k * 0.01, 0.1, 0.01, k * 0.1, 0.0, 0.0, 100.0, 0.01 * (k // 5)]
            for k in range(n)]


HEADER = ",".join(RUN_COLUMNS)


def test_missing_column_names_file_and_column(tmp_path):
    path = _write(tmp_path / "run_a.csv", HEADER.replace(",yaw_rate", ""),
                  [row[:3] + row[4:] for row in _good_rows()])
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    print(info.value)
    assert "run_a.csv" in str(info.value) and "'yaw_rate'" in str(info.value)


@pytest.mark.parametrize("bad", ["nan", "inf", ""])
def test_nan_row_names_file_and_column(tmp_path, bad):
    rows = _good_rows()
    rows[7][2] = bad
    _write(tmp_path / "run_b.csv", HEADER, rows)
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    print(info.value)
    assert "run_b.csv" in str(info.value) and "'vy'" in str(info.value) and "row 8" in str(info.value)


def test_non_monotonic_time_is_rejected(tmp_path):
    rows = _good_rows()
    rows[5][0], rows[6][0] = rows[6][0], rows[5][0]
    _write(tmp_path / "run_c.csv", HEADER, rows)
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    print(info.value)
    assert "run_c.csv" in str(info.value) and "'time'" in str(info.value) and "increasing" in str(info.value)


def test_gap_is_rejected(tmp_path):
    rows = _good_rows()
    for row in rows[10:]:
        row[0] += 0.5
    _write(tmp_path / "run_d.csv", HEADER, rows)
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    print(info.value)
    assert "run_d.csv" in str(info.value) and "'time'" in str(info.value) and "gap" in str(info.value)


def test_empty_or_missing_directory_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="no \\*.csv"):
        load_dataset(tmp_path)


def test_resampling_to_ts_interpolates_states_and_holds_inputs(tmp_path):
    dt = 0.01
    t = np.arange(0.0, 2.0 + 1e-9, dt)
    yaw = np.unwrap(np.angle(np.exp(1j * (3.0 + 1.5 * t))))  # crosses +-pi...
    yaw_wrapped = (yaw + np.pi) % (2 * np.pi) - np.pi         # ...stored wrapped
    columns = {"time": t, "vx": 10 + t, "vy": 0.1 * t, "yaw_rate": np.full_like(t, 1.5),
               "x": t, "y": -t, "yaw": yaw_wrapped, "torque": np.floor(t / 0.3) * 100.0,
               "steer": np.where(t >= 0.505, 0.1, 0.0)}
    write_run_csv(tmp_path / "run_e.csv", Run("run_e", columns))
    (run,) = load_dataset(tmp_path, ts=0.025)
    grid = np.arange(81) * 0.025
    err_vx = np.abs(run.columns["vx"] - (10 + grid)).max()
    err_yaw = np.abs(run.columns["yaw"] - (yaw[0] + 1.5 * grid)).max()
    print(f"resampled 10 ms -> 25 ms: {len(run)} samples, max vx error {err_vx:.1e}, "
          f"max yaw error (unwrapped) {err_yaw:.1e}")
    assert len(run) == 81 and np.allclose(run.time, grid)
    assert err_vx < 1e-9 and err_yaw < 1e-6
    # Inputs are held: the steer step at 0.505 s appears at the first grid time after it.
    assert run.columns["steer"][20] == 0.0 and run.columns["steer"][21] == 0.1
    assert run.array(["vx", "steer"]).shape == (81, 2)


def test_run_on_grid_is_unchanged(tmp_path):
    rows = _good_rows(40, 0.025)
    path = _write(tmp_path / "run_f.csv", HEADER, rows)
    raw = read_run_csv(path)
    same = resample(raw, 0.025)
    assert len(same) == 40
    for name in RUN_COLUMNS:
        assert np.array_equal(same.columns[name], raw.columns[name]), name

"""Training from a named-column CSV data set through the CLI (``--data/--states/--inputs/--ts``)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from models.koopman import KoopmanModel  # noqa: E402
from models.koopman_cli import main  # noqa: E402
from test_koopman_synthetic import synthetic_runs  # noqa: E402

TINY_ARGS = ["--features", "2", "--hidden", "8,8", "--seq-len", "5", "--epochs", "1", "--steps-per-epoch", "5",
             "--batch-size", "16", "--no-progress"]


def write_external_dataset(directory: Path, nan_row: int | None = None) -> None:
    """Runs with foreign column names: speed, lat_vel, yaw_rate / throttle, brake, steer."""
    directory.mkdir()
    for run in synthetic_runs(n_runs=4, n_samples=120, seed=7):
        time = np.arange(len(run)) * 0.025
        throttle = np.clip(run.inputs[:, 0], 0, None)
        brake = np.clip(-run.inputs[:, 0], 0, None)
        table = np.column_stack([time, run.states, throttle, brake, run.inputs[:, 1]])
        if nan_row is not None:
            table[nan_row, 2] = np.nan
        np.savetxt(directory / f"{run.name}.csv", table, delimiter=",", comments="",
                   header="time,speed,lat_vel,yaw_rate,throttle,brake,steer", fmt="%.9g")


def test_external_dataset_with_named_columns(tmp_path: Path) -> None:
    write_external_dataset(tmp_path / "ext")
    out = tmp_path / "model"
    code = main(["--data", str(tmp_path / "ext"), "--out", str(out), "--states", "speed,lat_vel,yaw_rate",
                 "--inputs", "throttle,brake,steer", "--ts", "0.0125", *TINY_ARGS])
    assert code == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["state_names"] == ["speed", "lat_vel", "yaw_rate"]
    assert meta["input_names"] == ["throttle", "brake", "steer"]
    assert meta["ts"] == 0.0125 and meta["data_hash"].startswith("sha256:")
    model = KoopmanModel.load(out.with_suffix(".npz"))
    assert (model.n_x, model.n_u, model.n_z) == (3, 3, 5)


def test_missing_column_is_a_clear_error(tmp_path: Path, capsys) -> None:
    write_external_dataset(tmp_path / "ext")
    code = main(["--data", str(tmp_path / "ext"), "--out", str(tmp_path / "m"), "--states", "speed,lat_vel,yaw_rate",
                 "--inputs", "throttle,clutch", *TINY_ARGS])
    err = capsys.readouterr().err
    print(err.strip())
    assert code == 2 and err.startswith("error: ") and "'clutch'" in err


def test_nan_row_is_a_clear_error(tmp_path: Path, capsys) -> None:
    write_external_dataset(tmp_path / "ext", nan_row=30)
    code = main(["--data", str(tmp_path / "ext"), "--out", str(tmp_path / "m"), "--states", "speed,lat_vel,yaw_rate",
                 "--inputs", "throttle,brake,steer", *TINY_ARGS])
    err = capsys.readouterr().err
    print(err.strip())
    assert code == 2 and "lat_vel" in err and "NaN" in err


def test_dataset_too_short_for_p_is_a_clear_error(tmp_path: Path, capsys) -> None:
    write_external_dataset(tmp_path / "ext")
    code = main(["--data", str(tmp_path / "ext"), "--out", str(tmp_path / "m"), "--states", "speed,lat_vel,yaw_rate",
                 "--inputs", "throttle,brake,steer", *TINY_ARGS, "--seq-len", "500"])
    err = capsys.readouterr().err
    print(err.strip())
    assert code == 2 and "too short for sequences of length p=500" in err


def test_the_split_is_explicit_and_reported_and_the_knots_follow_the_data(tmp_path: Path, capsys) -> None:
    """--val-runs / --test-runs put those runs there and the rest trains; the report lists
    every run's set; the default speed knots are those inside the data's speed range."""
    write_external_dataset(tmp_path / "ext")
    names = sorted(p.stem for p in (tmp_path / "ext").glob("*.csv"))
    out = tmp_path / "model"
    code = main(["--data", str(tmp_path / "ext"), "--out", str(out), "--states", "speed,lat_vel,yaw_rate",
                 "--inputs", "throttle,brake,steer", "--val-runs", names[0], "--test-runs", f"{names[1]},{names[2]}",
                 *TINY_ARGS])
    assert code == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["split"] == {"train": [names[3]], "validation": [names[0]], "test": [names[1], names[2]]}
    printed = capsys.readouterr().out
    assert f"test runs (2): {names[1]}, {names[2]}" in printed
    speeds = np.concatenate([np.loadtxt(p, delimiter=",", skiprows=1)[:, 1] for p in (tmp_path / "ext").glob("*.csv")])
    knots = meta["settings"]["speed_knots"]
    assert speeds.min() <= knots[0] and knots[-1] <= speeds.max() and len(knots) >= 2


def test_a_run_named_twice_or_unknown_and_an_option_without_its_columns_are_one_line(tmp_path: Path, capsys) -> None:
    write_external_dataset(tmp_path / "ext")
    names = sorted(p.stem for p in (tmp_path / "ext").glob("*.csv"))
    base = ["--data", str(tmp_path / "ext"), "--out", str(tmp_path / "m"), "--states", "speed,lat_vel,yaw_rate",
            "--inputs", "throttle,brake,steer", *TINY_ARGS]
    assert main([*base, "--test-runs", "nosuchrun"]) == 2
    assert "not in the data: ['nosuchrun']" in capsys.readouterr().err
    assert main([*base, "--val-runs", names[0], "--test-runs", names[0]]) == 2
    assert "val_runs" in capsys.readouterr().err
    assert main([*base, "--form", "scheduled", "--mirror-symmetric", "--servo-lag"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--servo-lag needs the column(s) ['steer_measured']" in err
    assert not (tmp_path / "m.npz").exists()


def test_knots_in_range_keeps_the_inner_knots_or_takes_the_ends() -> None:
    from models.koopman_settings import knots_in_range

    assert knots_in_range((3.0, 6.0, 10.0, 15.0, 20.0, 27.0, 35.0), 2.0, 36.6) == (3.0, 6.0, 10.0, 15.0, 20.0,
                                                                                  27.0, 35.0)
    assert knots_in_range((3.0, 6.0, 10.0, 15.0, 20.0, 27.0, 35.0), 0.5, 17.6) == (3.0, 6.0, 10.0, 15.0)
    assert knots_in_range((3.0, 6.0, 10.0), 3.5, 5.0) == (3.5, 5.0)

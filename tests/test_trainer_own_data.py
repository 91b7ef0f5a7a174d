"""The trainer on a user's data (docs/own-data.md): the speed knots of ``--logs`` come from
the data as those of ``--data`` do; ``--compare-with`` puts another form beside the trained
model on the same test runs; inputs of any name (throttle, brake, steer) are held when
resampled and train every form."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from models.dataset import load_dataset
from models.koopman import KoopmanModel
from models.koopman_cli import main
from models.koopman_data import load_trajectories
from models.koopman_metrics import OPEN_LOOP_STEPS, prediction_errors
from models.koopman_settings import TrainingSettings, knots_in_range
from test_koopman_synthetic import synthetic_runs

#: A network small enough to train in about a second.
TINY = ["--features", "2", "--hidden", "8,8", "--seq-len", "5", "--epochs", "1", "--steps-per-epoch", "3",
        "--batch-size", "16", "--no-progress"]
FOREIGN_INPUTS = "throttle,brake,steer"


def _write_runs(directory: Path, file_step: float = 0.025, n_runs: int = 5) -> list[Path]:
    """Synthetic runs (vx 8-20 m/s) with a throttle, a brake and a steer command, each input
    a staircase that steps between two file rows. ``file_step``: the files' sample time
    (the runs' states are at 25 ms and interpolated onto it)."""
    directory.mkdir()
    rng = np.random.default_rng(11)
    paths = []
    for run in synthetic_runs(n_runs=n_runs, n_samples=160, seed=7):
        grid = np.arange(len(run)) * 0.025
        time = np.arange(0.0, grid[-1] + 1e-9, file_step)
        states = np.column_stack([np.interp(time, grid, run.states[:, j]) for j in range(3)])
        steps = np.repeat(rng.uniform(0.0, 1.0, size=(len(time) // 7 + 1, 3)), 7, axis=0)[: len(time)]
        table = np.column_stack([time, states, steps])
        path = directory / f"{run.name}.csv"
        np.savetxt(path, table, delimiter=",", comments="", fmt="%.10g",
                   header=f"time,vx,vy,yaw_rate,{FOREIGN_INPUTS}")
        paths.append(path)
    return paths


# ---------------------------------------------------------------- 1. knots of --logs
def test_logs_take_the_speed_knots_from_the_data_as_data_does(tmp_path: Path, capsys) -> None:
    """The same runs through ``--data`` and through ``--logs`` with a mapping get the same
    knots: those of the defaults inside the data's speed range, never 27 or 35 m/s on data
    that stop below 20 m/s."""
    pytest.importorskip("torch")
    files = _write_runs(tmp_path / "runs")
    mapping = tmp_path / "map.toml"
    mapping.write_text('sample_time_s = 0.025\ntime_column = "time"\n'
                       '[states]\nvx = "vx"\nvy = "vy"\nyaw_rate = "yaw_rate"\n'
                       '[inputs]\nthrottle = "throttle"\nbrake = "brake"\nsteer = "steer"\n')
    assert main(["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
                 "--out", str(tmp_path / "from_data"), *TINY]) == 0
    assert main(["--logs", *map(str, files), "--mapping", str(mapping), "--out", str(tmp_path / "from_logs"),
                 *TINY]) == 0
    printed = capsys.readouterr().out
    from_data = json.loads((tmp_path / "from_data.json").read_text())["settings"]["speed_knots"]
    from_logs = json.loads((tmp_path / "from_logs" / "koopman.json").read_text())["settings"]["speed_knots"]
    speeds = np.concatenate([np.loadtxt(path, delimiter=",", skiprows=1)[:, 1] for path in files])
    print(f"speeds {speeds.min():.2f}-{speeds.max():.2f} m/s: knots --data {from_data}, --logs {from_logs}")
    assert from_logs == from_data == list(knots_in_range(TrainingSettings().speed_knots, speeds.min(), speeds.max()))
    assert from_logs[-1] <= speeds.max() < 27.0
    assert printed.count("note: speed knots") == 2


# ---------------------------------------------------------------- 2. --compare-with another form
def test_compare_with_another_form_runs_it_on_the_same_test_runs(tmp_path: Path, capsys) -> None:
    _write_runs(tmp_path / "runs")
    base = ["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
            "--no-progress"]
    assert main([*base, "--form", "edmdc-linear", "--out", str(tmp_path / "linear")]) == 0
    assert main([*base, "--form", "edmdc-bilinear", "--out", str(tmp_path / "bilinear"),
                 "--compare-with", str(tmp_path / "linear.json")]) == 0
    printed = capsys.readouterr().out
    print(printed[-1500:])
    assert "compared with" in printed and "not compared" not in printed
    bilinear = json.loads((tmp_path / "bilinear.json").read_text())
    test_names = bilinear["split"]["test"]
    runs = {run.name: run for run in load_trajectories(tmp_path / "runs", ("vx", "vy", "yaw_rate"),
                                                       tuple(FOREIGN_INPUTS.split(",")))}
    other = prediction_errors(KoopmanModel.load(tmp_path / "linear"), [runs[n] for n in test_names],
                              OPEN_LOOP_STEPS)
    # each state's row: this model's figure and the other model's on this training's test runs
    for state in ("vx", "vy", "yaw_rate"):
        row = re.search(rf"^\s+{state} open_loop_rmse \({OPEN_LOOP_STEPS} steps\)\s+(\S+)\s+(\S+)", printed, re.M)
        assert row is not None, state
        assert float(row.group(1)) == pytest.approx(bilinear["test_errors"][state]["open_loop_rmse"], abs=1e-5)
        assert float(row.group(2)) == pytest.approx(other[state]["open_loop_rmse"], abs=1e-5)


def test_compare_with_the_same_settings_is_the_reproduction_check(tmp_path: Path, capsys) -> None:
    _write_runs(tmp_path / "runs")
    base = ["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
            "--form", "edmdc-linear", "--no-progress"]
    assert main([*base, "--out", str(tmp_path / "first")]) == 0
    (tmp_path / "first.npz").unlink()   # make train keeps only the JSON of the previous artefact
    assert main([*base, "--out", str(tmp_path / "again"), "--compare-with", str(tmp_path / "first.json")]) == 0
    assert "largest relative change vs" in capsys.readouterr().out
    meta = json.loads((tmp_path / "first.json").read_text())
    meta["test_errors"]["vy"]["open_loop_rmse"] *= 2.0
    (tmp_path / "off.json").write_text(json.dumps(meta))
    assert main([*base, "--out", str(tmp_path / "third"), "--compare-with", str(tmp_path / "off.json")]) == 3
    # the same settings on another split (a closed-form fit records no seed) is no reproduction
    capsys.readouterr()
    assert main([*base, "--seed", "1", "--out", str(tmp_path / "fourth"),
                 "--compare-with", str(tmp_path / "first.json")]) == 0
    printed = capsys.readouterr().out
    assert "its test runs differ" in printed and "largest relative change" not in printed


def test_compare_with_a_model_of_other_columns_is_refused_before_fitting(tmp_path: Path, capsys) -> None:
    _write_runs(tmp_path / "runs")
    base = ["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--no-progress", "--form", "edmdc-linear"]
    assert main([*base, "--inputs", "throttle,steer", "--out", str(tmp_path / "two_inputs")]) == 0
    capsys.readouterr()
    assert main([*base, "--inputs", FOREIGN_INPUTS, "--out", str(tmp_path / "three_inputs"),
                 "--compare-with", str(tmp_path / "two_inputs.json")]) == 2
    err = capsys.readouterr().err
    print(err)
    assert err.count("\n") == 1 and err.startswith("error: --compare-with") and "cannot run on these data" in err
    assert not (tmp_path / "three_inputs.npz").exists()


# ---------------------------------------------------------------- 4. inputs of other names
def test_inputs_of_any_name_are_held_when_resampled(tmp_path: Path) -> None:
    """10 ms files resampled to 25 ms: a throttle, brake and steer staircase keeps the value
    of the last file row at or before each grid time, never a blend of two steps."""
    _write_runs(tmp_path / "runs", file_step=0.01, n_runs=1)
    path = next((tmp_path / "runs").glob("*.csv"))
    raw = np.loadtxt(path, delimiter=",", skiprows=1)
    (run,) = load_trajectories(tmp_path / "runs", ("vx", "vy", "yaw_rate"), tuple(FOREIGN_INPUTS.split(",")), 0.025)
    grid = raw[0, 0] + 0.025 * np.arange(len(run))
    held = raw[np.searchsorted(raw[:, 0], grid + 1e-12, side="right") - 1, 4:7]
    print(f"largest difference to the held inputs: {np.abs(run.inputs - held).max():.2e}")
    assert np.array_equal(run.inputs, held)
    assert np.allclose(run.states[:, 0], np.interp(grid, raw[:, 0], raw[:, 1]))   # states interpolated
    # the default inputs are held as before
    (default_run,) = load_dataset(tmp_path / "runs", 0.025, ("time", "vx", "steer"))
    assert np.array_equal(default_run.columns["steer"], held[:, 2])


@pytest.mark.parametrize("form", ["edmdc-linear", "edmdc-bilinear", "scheduled"])
def test_every_form_trains_on_throttle_brake_and_steer(tmp_path: Path, form: str, capsys) -> None:
    if form == "scheduled":
        pytest.importorskip("torch")
    _write_runs(tmp_path / "runs")
    assert main(["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
                 "--form", form, "--out", str(tmp_path / "model"),
                 *(TINY if form == "scheduled" else ["--no-progress"])]) == 0  # the network's options refused otherwise
    model = KoopmanModel.load(tmp_path / "model")
    assert model.input_names == ("throttle", "brake", "steer") and model.n_u == 3


@pytest.mark.parametrize(("options", "named"), [
    (["--mirror-symmetric"], "no parity known for ['throttle', 'brake']"),
    (["--gain-anchor", "10"], "--gain-anchor needs the column(s) ['steer_measured', 'torque']"),
    (["--mirror-symmetric", "--steer-bilinear", "--inputs", "throttle,brake"], "no parity known"),
    (["--gain-anchor", "10", "--gain-anchor-vy", "10"],
     "--gain-anchor-vy needs the column(s) ['steer_measured', 'torque']"),
    (["--gain-anchor-vy", "10"], "gain_anchor_vy=10.0 is invalid"),  # the vy term without the yaw anchor
])
def test_options_for_our_inputs_are_one_error_line_naming_what_is_missing(tmp_path: Path, capsys, options,
                                                                          named) -> None:
    pytest.importorskip("torch")
    _write_runs(tmp_path / "runs")
    assert main(["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
                 "--out", str(tmp_path / "model"), *TINY, *options]) == 2
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and err.count("\n") == 1 and named in err
    assert not (tmp_path / "model.npz").exists()

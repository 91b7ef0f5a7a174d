"""The test runs against the training data's state range (models/range_coverage.py): which
samples lie beyond it, the figures on the stretches within, and the trainer's warning."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.koopman_cli import main
from models.koopman_metrics import Trajectory, prediction_errors
from models.range_coverage import coverage_lines, held_out_coverage, range_split, state_range, within_stretches
from test_trainer_own_data import FOREIGN_INPUTS, _write_runs

STATES = ("vx", "vy")
INPUTS = ("u",)


def _run(name: str, vx: np.ndarray) -> Trajectory:
    n = len(vx)
    return Trajectory(name, np.column_stack([vx, np.linspace(-0.1, 0.1, n)]), np.arange(n, dtype=float)[:, None],
                      STATES, INPUTS)


class _HoldsWithinTen:
    """Holds the state (exact on a constant vx) where vx >= 10 m/s; adds 1 m/s per step below."""

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        steps = inputs.shape[1]
        out = np.repeat(x0[:, None, :], steps, axis=1)
        out[:, :, 0] += np.where(x0[:, 0] < 10.0, 1.0, 0.0)[:, None] * np.arange(1, steps + 1)
        return out


def test_stretches_split_at_the_samples_beyond_the_range_and_keep_their_inputs() -> None:
    vx = np.full(100, 12.0)
    vx[[0, 40, 41, 99]] = 5.0
    stretches = within_stretches([_run("r", vx)], np.array([10.0, -1.0]), np.array([20.0, 1.0]))
    assert [s.name for s in stretches] == ["r[1:40]", "r[42:99]"]
    assert [len(s) for s in stretches] == [39, 57]
    assert stretches[1].inputs[0, 0] == 42.0
    assert all(np.all(s.states[:, 0] == 12.0) for s in stretches)


def test_coverage_names_the_runs_beyond_and_measures_only_the_stretches_within() -> None:
    train = [_run("train", np.linspace(10.0, 20.0, 200))]
    inside = _run("inside", np.full(120, 15.0))
    slow = np.full(200, 15.0)
    slow[50:150] = 6.0  # below the slowest training sample
    test = [inside, _run("slow", slow)]
    coverage = held_out_coverage(_HoldsWithinTen(), train, test, open_loop_steps=10)
    assert coverage["training_min"]["vx"] == 10.0 and coverage["training_max"]["vx"] == 20.0
    assert coverage["outside"] == [{"run": "slow", "state": "vx", "samples": 100, "of": 200, "low": 6.0, "high": 15.0}]
    assert coverage["test_samples"] == 320 and coverage["within_samples"] == 220
    # the model is exact within the range and wrong below it: all figures within are zero
    assert coverage["within_errors"]["vx"]["open_loop_rmse"] == 0.0
    assert prediction_errors(_HoldsWithinTen(), test, open_loop_steps=10)["vx"]["open_loop_rmse"] > 1.0
    split, stretches = range_split(train, test)  # the same without a model
    assert split == {k: v for k, v in coverage.items() if k != "within_errors"}
    assert [s.name for s in stretches] == ["inside[0:120]", "slow[0:50]", "slow[150:200]"]
    lines = coverage_lines(coverage)
    assert lines[0].startswith("test run slow: 100 of 200 samples have vx outside the training data's 10 .. 20")
    assert lines[-1].startswith("within the training range (69 % of the test samples): vx one-step rmse 0.0000")


def test_coverage_is_silent_when_every_test_sample_lies_within() -> None:
    train = [_run("train", np.linspace(10.0, 20.0, 200))]
    coverage = held_out_coverage(_HoldsWithinTen(), train, [_run("t", np.full(60, 11.0))], open_loop_steps=10)
    assert coverage["outside"] == [] and coverage_lines(coverage) == []
    low, high = state_range(train)
    assert list(low) == [10.0, -0.1] and list(high) == [20.0, 0.1]


def test_no_stretch_long_enough_gives_no_figures_and_says_so() -> None:
    train = [_run("train", np.linspace(10.0, 20.0, 200))]
    vx = np.full(60, 15.0)
    vx[::5] = 3.0
    coverage = held_out_coverage(_HoldsWithinTen(), train, [_run("t", vx)], open_loop_steps=10)
    assert coverage["within_errors"] is None
    assert coverage_lines(coverage)[-1] == "no test stretch within the training range is long enough for the open-loop figures"


def test_the_trainer_warns_of_a_test_run_beyond_the_training_speeds(tmp_path: Path, capsys) -> None:
    """A test run driven slower than every training run: the trainer prints the warning and
    the figures within the range, and leaves the artefact's metadata as it was."""
    files = _write_runs(tmp_path / "runs")
    speeds = {path.stem: np.loadtxt(path, delimiter=",", skiprows=1)[:, 1] for path in files}
    slowest = min(speeds, key=lambda name: speeds[name].min())
    others = [name for name in speeds if name != slowest]
    assert speeds[slowest].min() < min(speeds[name].min() for name in others)
    assert main(["--data", str(tmp_path / "runs"), "--states", "vx,vy,yaw_rate", "--inputs", FOREIGN_INPUTS,
                 "--form", "edmdc-linear", "--no-progress", "--out", str(tmp_path / "model"),
                 "--test-runs", slowest, "--val-runs", others[0]]) == 0
    printed = capsys.readouterr().out
    assert f"warning: test run {slowest}: " in printed and "samples have vx outside the training data's" in printed
    training_min = min(speeds[name].min() for name in others[1:])
    assert f"the training data's {training_min:.4g} .. " in printed
    # this slow run stays within the range for fewer than 40 steps at a time
    assert printed.rstrip().endswith("warning: no test stretch within the training range is long enough for the "
                                     "open-loop figures")
    assert "test_coverage" not in json.loads((tmp_path / "model.json").read_text())

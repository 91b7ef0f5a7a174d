"""Least-squares lifted models (models/lifted_least_squares.py): the closed-form fit recovers
a system that is linear (or bilinear) in its lift, loads as a Koopman artefact, and the
trainer's command line offers it as --form edmdc-linear / edmdc-bilinear."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.koopman import KoopmanError, KoopmanModel
from models.koopman_artifact import save_artifact
from models.koopman_cli import main
from models.koopman_metrics import Trajectory
from models.koopman_settings import TrainingSettings
from models.lifted_least_squares import PHYSICS_DICTIONARY, fit_least_squares
from test_koopman_synthetic import synthetic_runs

A_TRUE = np.array([[0.95, 0.02], [-0.05, 0.9]])
B_TRUE = np.array([[0.1], [0.3]])
C_TRUE = np.array([0.01, -0.02])
N_TRUE = np.array([[[0.02, 0.0], [0.0, -0.03]]])  # (n_u, n_x, n_x)


def _runs(bilinear: bool, n_runs: int = 6) -> list[Trajectory]:
    """Runs of x+ = A x + B u + c (+ u N x) with random inputs: exact in the lift z = x."""
    rng = np.random.default_rng(5)
    runs = []
    for k in range(n_runs):
        u = rng.uniform(-1.0, 1.0, size=(300, 1))
        x = np.zeros((300, 2))
        x[0] = rng.uniform(-1.0, 1.0, size=2)
        for i in range(299):
            x[i + 1] = A_TRUE @ x[i] + B_TRUE @ u[i] + C_TRUE + (u[i, 0] * N_TRUE[0] @ x[i] if bilinear else 0.0)
        runs.append(Trajectory(f"run_{k}", x, u, ("a", "b"), ("u",)))
    return runs


@pytest.mark.parametrize("bilinear", [False, True])
def test_the_fit_recovers_a_system_exact_in_its_lift(bilinear: bool, tmp_path: Path) -> None:
    form = "edmdc-bilinear" if bilinear else "edmdc-linear"
    result = fit_least_squares(_runs(bilinear), 0.025, form, TrainingSettings())
    model = result.model
    assert model.n_z == 2 and model.form == ("bilinear" if bilinear else "linear")
    assert np.allclose(model.A, A_TRUE, atol=1e-6) and np.allclose(model.B, B_TRUE, atol=1e-6)
    assert np.allclose(model.offset, C_TRUE, atol=1e-6)
    if bilinear:
        assert np.allclose(model.N, N_TRUE, atol=1e-6)
    assert model.metadata["test_errors"]["a"]["one_step_rmse"] < 1e-6
    # through the artefact files, as the ECUs load it
    save_artifact(tmp_path / "m", result.learned, model.metadata)
    loaded = KoopmanModel.load(tmp_path / "m")
    assert np.allclose(loaded.A, model.A, atol=1e-12) and loaded.n_features == 0


def test_our_states_get_the_physics_dictionary_and_a_split_by_run() -> None:
    runs = synthetic_runs(n_runs=6, n_samples=200, seed=3)
    result = fit_least_squares(runs, 0.025, "edmdc-bilinear", TrainingSettings(test_runs=("synthetic_01",)))
    assert result.model.dictionary == PHYSICS_DICTIONARY and result.model.n_z == 3 + len(PHYSICS_DICTIONARY)
    assert result.test_runs == ["synthetic_01"] and "synthetic_01" not in result.train_runs
    with pytest.raises(KoopmanError, match="least-squares form"):
        fit_least_squares(runs, 0.025, "edmdc-cubic", TrainingSettings())


def test_the_command_line_fits_in_closed_form(tmp_path: Path, capsys) -> None:
    data = tmp_path / "data"
    data.mkdir()
    for run in _runs(True, n_runs=4):
        table = np.column_stack([np.arange(len(run.states)) * 0.025, run.states, run.inputs])
        np.savetxt(data / f"{run.name}.csv", table, delimiter=",", header="time,a,b,u", comments="", fmt="%.12g")
    out = tmp_path / "lsq"
    assert main(["--data", str(data), "--states", "a,b", "--inputs", "u", "--form", "edmdc-bilinear",
                 "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "fitted in closed form" in printed and "test runs (1)" in printed
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["form"] == "bilinear" and meta["settings"]["form"] == "edmdc-bilinear"
    assert np.allclose(KoopmanModel.load(out).N, N_TRUE, atol=1e-6)


def _csv_runs(folder: Path) -> Path:
    """Four bilinear runs as named-column CSVs (time, a, b, u) in ``folder``/data."""
    data = folder / "data"
    data.mkdir()
    for run in _runs(True, n_runs=4):
        table = np.column_stack([np.arange(len(run.states)) * 0.025, run.states, run.inputs])
        np.savetxt(data / f"{run.name}.csv", table, delimiter=",", header="time,a,b,u", comments="", fmt="%.12g")
    return data


@pytest.mark.parametrize("form", ["edmdc-linear", "edmdc-bilinear"])
@pytest.mark.parametrize("option", [
    ["--epochs", "5"], ["--epochs=120"], ["--features", "8"], ["--learning-rate", "1e-3"], ["--gain-anchor", "1"],
    ["--mirror-symmetric"], ["--servo-lag"], ["--speed-knots", "5,10"], ["--hidden", "32,32"], ["--device", "cpu"],
    ["--threads", "2"], ["--seq-len", "11"], ["--lifted-weight", "0.5"], ["--patience", "3"],
    ["--epo", "5"],  # an abbreviation argparse accepts names the option in full
])
def test_options_of_the_network_are_refused_for_a_closed_form_fit(tmp_path: Path, capsys, form: str,
                                                                   option: list[str]) -> None:
    """Once silently ignored (the fit ran and wrote an artefact that did not use them); the
    default value given explicitly (``--epochs=120``) is refused too."""
    out = tmp_path / "lsq"
    assert main(["--data", str(_csv_runs(tmp_path)), "--states", "a,b", "--inputs", "u", "--form", form,
                 "--out", str(out), "--no-progress", *option]) == 2
    error = capsys.readouterr().err.strip()
    name = option[0].split("=")[0]
    name = "--epochs" if name == "--epo" else name
    assert error.count("\n") == 0 and error.startswith("error: ") and name in error and form in error
    assert not out.with_suffix(".npz").exists() and not out.with_suffix(".json").exists()


def test_every_option_is_either_for_the_network_only_or_for_both_kinds_of_fit() -> None:
    """A new option must be sorted into one of the two, so the refusal keeps up with the parser."""
    from models.koopman_cli import DEEP_ONLY_OPTIONS, build_parser

    both = {"--help", "--data", "--out", "--replace", "--states", "--inputs", "--ts", "--form", "--dictionary",
            "--val-runs", "--test-runs", "--val-fraction", "--test-fraction", "--seed", "--compare-with", "--logs",
            "--log-inputs", "--mapping", "--vehicle", "--dbc", "--no-progress", "--debug"}
    options = {action.option_strings[-1] for action in build_parser()._actions}
    assert set(DEEP_ONLY_OPTIONS) <= options and not set(DEEP_ONLY_OPTIONS) & both
    assert options == set(DEEP_ONLY_OPTIONS) | both


def test_the_split_and_the_dictionary_still_apply_to_a_closed_form_fit(tmp_path: Path) -> None:
    out = tmp_path / "lsq"
    assert main(["--data", str(_csv_runs(tmp_path)), "--states", "a,b", "--inputs", "u", "--form", "edmdc-linear",
                 "--out", str(out), "--no-progress", "--seed", "3", "--test-runs", "run_2", "--dictionary", ""]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["split"]["test"] == ["run_2"] and meta["seed"] == 3

"""Deep Koopman training (torch): numpy/torch agreement, determinism, split, bad input, CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.koopman import KoopmanError, KoopmanModel, dictionary_features, knot_weights  # noqa: E402
from models.koopman_cli import main  # noqa: E402
from models.koopman_metrics import Trajectory  # noqa: E402
from models.koopman_train import (  # noqa: E402
    SequenceSet,
    TrainingSettings,
    fit_scaling,
    settings_json,
    split_runs,
    train,
    window_weights,
    write_artifact,
)
from test_koopman_synthetic import INPUTS, STATES, synthetic_runs  # noqa: E402

TINY = TrainingSettings(n_features=3, hidden=(16, 16, 16), seq_len=6, batch_size=32, max_epochs=2,
                        steps_per_epoch=15, patience=2, val_windows=256, threads=1)


@pytest.fixture(scope="module")
def runs() -> list[Trajectory]:
    return synthetic_runs(n_runs=5, n_samples=160, seed=3)


@pytest.fixture(scope="module")
def tiny_result(runs):
    return train(runs, 0.025, TINY, progress=False)


FORMS = {"scheduled": {}, "linear": {"form": "linear"},
         "bilinear": {"form": "bilinear", "dictionary": ("vy/vx", "r/vx", "vx*r", "vx^2/100")}}


@pytest.mark.parametrize("form", FORMS)
def test_numpy_run_time_agrees_with_torch(tiny_result, runs, form) -> None:
    """Lift and a 40-step rollout: torch (float64, normalised units) vs the numpy model, each form."""
    result = tiny_result if form == "scheduled" else train(
        runs, 0.025, TrainingSettings(**{**TINY.__dict__, **FORMS[form]}), progress=False)
    assert result.model.form == form
    net = result.net.double()
    model = result.model
    learned = result.learned
    sx, su = learned.state_scaling, learned.input_scaling
    rng = np.random.default_rng(0)
    states = np.concatenate([r.states for r in runs])
    inputs = np.concatenate([r.inputs for r in runs])
    x0 = rng.uniform(states.min(0), states.max(0), (64, 3))
    u = rng.uniform(inputs.min(0), inputs.max(0), (64, 40, 2))
    psi = (learned.dictionary_scaling.normalise(dictionary_features(learned.dictionary, x0))
           if learned.dictionary else np.zeros((64, 0)))
    weights = (torch.as_tensor(knot_weights(np.array(learned.speed_knots), x0[:, 0]))
               if learned.speed_knots else None)
    with torch.no_grad():
        z_n = net.lift(torch.as_tensor(sx.normalise(x0)), torch.as_tensor(psi))
        rolled = net.rollout(z_n, torch.as_tensor(su.normalise(u)), weights).numpy()
    known = 3 + len(learned.dictionary)  # the dictionary is physical in numpy, normalised in torch
    torch_features = z_n.numpy()[:, known:]
    torch_states = rolled[..., :3] * (sx.high - sx.low) + sx.low
    err_lift = np.abs(model.lift(x0)[:, known:] - torch_features).max()
    err_pred = np.abs(model.predict(x0, u) - torch_states).max()
    print(f"max |numpy - torch|: lift {err_lift:.2e}, 40-step prediction {err_pred:.2e}")
    assert err_lift < 1e-6 and err_pred < 1e-6


def test_same_seed_gives_identical_weights(runs, tiny_result) -> None:
    again = train(runs, 0.025, TINY, progress=False)
    other = train(runs, 0.025, TrainingSettings(**{**TINY.__dict__, "seed": 1}), progress=False)
    first, second = tiny_result.learned, again.learned
    diffs = [np.abs(a[0] - b[0]).max() for a, b in zip(first.encoder, second.encoder)]
    diffs.append(np.abs(first.A_n - second.A_n).max())  # scheduled: one A per knot
    print(f"max weight difference, same seed: {max(diffs):.1e}; "
          f"other seed: {np.abs(first.A_n - other.learned.A_n).max():.1e}")
    assert max(diffs) == 0.0
    assert np.array_equal(first.B_n, second.B_n)
    assert not np.array_equal(first.A_n, other.learned.A_n)


def test_split_is_by_run_and_scaling_from_training_runs(runs, tiny_result) -> None:
    train_runs, val_runs, test_runs = split_runs(runs, TINY)
    names = [{r.name for r in part} for part in (train_runs, val_runs, test_runs)]
    assert all(names) and not (names[0] & names[1] or names[0] & names[2] or names[1] & names[2])
    assert set().union(*names) == {r.name for r in runs}
    assert tiny_result.test_runs == [r.name for r in test_runs]
    state_scaling, _ = fit_scaling(train_runs)
    np.testing.assert_array_equal(tiny_result.learned.state_scaling.low, state_scaling.low)


def test_metadata_holds_what_the_artifact_needs(tiny_result, tmp_path: Path) -> None:
    npz_path, json_path = write_artifact(tiny_result, tmp_path / "dk_tiny")
    meta = json.loads(json_path.read_text())
    for key in ("d", "ts", "state_min", "state_max", "input_min", "input_max", "state_names", "input_names",
                "settings", "seed", "test_errors", "split", "spectral_radius_A"):
        assert key in meta, key
    assert set(meta["test_errors"]) == set(STATES)
    loaded = KoopmanModel.load(npz_path)
    np.testing.assert_array_equal(loaded.A, tiny_result.model.A)


def test_learning_beats_the_initial_model(runs) -> None:
    """From a cold start (no least-squares warm start) a few hundred steps must lower the
    validation loss well below the first epoch's."""
    settings = TrainingSettings(**{**TINY.__dict__, "max_epochs": 6, "steps_per_epoch": 30, "patience": 6,
                                   "warm_start": False, "form": "linear", "learning_rate": 1e-3})
    result = train(runs, 0.025, settings, progress=False)
    losses = [h["val"] for h in result.history]
    print("validation loss per epoch:", ", ".join(f"{v:.2e}" for v in losses))
    assert min(losses) < 0.7 * losses[0]


def test_too_few_runs_or_too_short_runs_are_refused(runs) -> None:
    with pytest.raises(KoopmanError, match="at least 3 runs"):
        train(runs[:2], 0.025, TINY, progress=False)
    short = [Trajectory(r.name, r.states[:5], r.inputs[:5], STATES, INPUTS) for r in runs]
    with pytest.raises(KoopmanError, match=r"too short for sequences of length p=6"):
        train(short, 0.025, TINY, progress=False)


def test_nan_rows_are_refused_naming_run_column_and_row(runs) -> None:
    states = runs[0].states.copy()
    states[17, 1] = np.nan
    with pytest.raises(KoopmanError, match=r"run synthetic_00: non-finite value in column 'vy' at row 17"):
        Trajectory(runs[0].name, states, runs[0].inputs, STATES, INPUTS)


def test_bad_settings_name_the_field() -> None:
    with pytest.raises(KoopmanError, match="seq_len=1"):
        TrainingSettings(seq_len=1)


def test_an_unscheduled_state_has_one_row_for_every_speed_knot(runs, tiny_result) -> None:
    """The yaw-rate row of (A, B, c) is the same at every knot; the others still differ."""
    result = train(runs, 0.025, TrainingSettings(**{**TINY.__dict__, "unscheduled_states": ("yaw_rate",)}),
                   progress=False)
    learned, row = result.learned, STATES.index("yaw_rate")
    for name, matrix in (("A", learned.A_n), ("B", learned.B_n), ("c", learned.affine_n)):
        spread = np.abs(matrix[:, row] - matrix[:1, row]).max()
        print(f"{name}: largest difference of the yaw-rate row between knots {spread:.1e}")
        assert spread < 1e-6
    assert np.abs(learned.A_n[:, 1] - learned.A_n[:1, 1]).max() > 1e-4  # vy stays scheduled
    assert np.abs(tiny_result.learned.A_n[:, row] - tiny_result.learned.A_n[:1, row]).max() > 1e-4


def test_small_signal_weighting_weighs_windows_by_their_peak_lateral_acceleration(runs, tiny_result) -> None:
    weights = window_weights(torch.tensor([0.0, 3.0, 6.0, 30.0]), 3.0).numpy()
    assert weights == pytest.approx([1.0, 0.5, 0.2, 1.0 / 101.0])
    state_scaling, input_scaling = fit_scaling(runs)
    windows = SequenceSet(runs[:1], 6, state_scaling, input_scaling, torch.device("cpu"), "training")
    lateral = np.abs(runs[0].states[:, 0] * runs[0].states[:, 2])
    expected = [lateral[k:k + 6].max() for k in range(len(runs[0]) - 5)]
    assert windows.peak_accel.numpy() == pytest.approx(expected, rel=1e-6)
    weighted = train(runs, 0.025, TrainingSettings(**{**TINY.__dict__, "small_signal_accel": 1.0}), progress=False)
    assert np.abs(weighted.learned.A_n - tiny_result.learned.A_n).max() > 1e-4  # the option acts


def test_training_options_are_recorded_only_when_on() -> None:
    assert "small_signal_accel" not in settings_json(TrainingSettings())
    assert "unscheduled_states" not in settings_json(TrainingSettings())
    on = settings_json(TrainingSettings(small_signal_accel=3.0, unscheduled_states=("steer_measured",)))
    assert on["small_signal_accel"] == 3.0 and on["unscheduled_states"] == ["steer_measured"]


def test_bad_training_options_are_refused(runs) -> None:
    with pytest.raises(KoopmanError, match="small_signal_accel=-1.0"):
        TrainingSettings(small_signal_accel=-1.0)
    with pytest.raises(KoopmanError, match="unscheduled_states"):
        TrainingSettings(form="linear", unscheduled_states=("vy",))
    with pytest.raises(KoopmanError, match=r"unscheduled_states \['steer_measured'\] are not among the states"):
        train(runs, 0.025, TrainingSettings(**{**TINY.__dict__, "unscheduled_states": ("steer_measured",)}),
              progress=False)


def test_cli_reports_a_missing_directory(tmp_path: Path, capsys) -> None:
    assert main(["--data", str(tmp_path / "absent"), "--out", str(tmp_path / "m"), "--no-progress"]) == 2
    assert "error: data directory not found" in capsys.readouterr().err

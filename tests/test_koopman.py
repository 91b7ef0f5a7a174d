"""Run-time deep Koopman model (numpy only): folding of the normalisation, shapes, I/O, errors."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from models.koopman import (
    DEFAULT_ARTIFACT,
    KoopmanError,
    KoopmanModel,
    MinMaxScaling,
    NormalisedKoopman,
    save_artifact,
)

REPO = Path(__file__).resolve().parents[1]
NAMES_X = ("vx", "vy", "yaw_rate")
NAMES_U = ("torque", "steer")


def random_learned(rng: np.random.Generator, n_features: int = 4, hidden: tuple[int, ...] = (16, 16)) -> NormalisedKoopman:
    widths = (3, *hidden, n_features)
    encoder = tuple(
        (rng.normal(0, 1 / np.sqrt(a), (b, a)), rng.normal(0, 0.1, b)) for a, b in zip(widths[:-1], widths[1:])
    )
    n_z = 3 + n_features
    return NormalisedKoopman(
        encoder=encoder,
        A_n=np.eye(n_z) + rng.normal(0, 0.02, (n_z, n_z)),
        B_n=rng.normal(0, 0.05, (n_z, 2)),
        state_scaling=MinMaxScaling(np.array([2.0, -1.5, -0.8]), np.array([30.0, 1.5, 0.8])),
        input_scaling=MinMaxScaling(np.array([-2000.0, -0.3]), np.array([3000.0, 0.3])),
    )


def reference_predict(learned: NormalisedKoopman, x0: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Straight from the definition, in normalised units: (features (batch, d), states (batch, n, 3))."""
    sx, su = learned.state_scaling, learned.input_scaling
    h = (x0 - sx.low) / (sx.high - sx.low)
    x_n = h
    for i, (w, b) in enumerate(learned.encoder):
        h = h @ w.T + b
        if i < len(learned.encoder) - 1:
            h = np.tanh(h)
    z_n = np.hstack([x_n, h])
    u_n = (inputs - su.low) / (su.high - su.low)
    states = []
    for k in range(inputs.shape[1]):
        z_n = z_n @ learned.A_n.T + u_n[:, k] @ learned.B_n.T
        states.append(z_n[:, :3] * (sx.high - sx.low) + sx.low)
    return h, np.stack(states, axis=1)


def test_physical_matrices_match_the_normalised_model() -> None:
    rng = np.random.default_rng(1)
    learned = random_learned(rng)
    model = KoopmanModel.from_normalised(learned, 0.025, NAMES_X, NAMES_U)
    x0 = rng.uniform([5, -1, -0.5], [25, 1, 0.5], (16, 3))
    inputs = rng.uniform([-1000, -0.2], [2000, 0.2], (16, 40, 2))
    features, states = reference_predict(learned, x0, inputs)
    lifted = model.lift(x0)
    predicted = model.predict(x0, inputs)
    err_lift = np.abs(lifted - np.hstack([x0, features])).max()
    err_pred = np.abs(predicted - states).max()
    print(f"max |lift - reference| = {err_lift:.2e}, max |predict - reference| over 40 steps = {err_pred:.2e}")
    assert err_lift < 1e-10 and err_pred < 1e-9
    assert np.array_equal(model.C_P @ lifted[0], x0[0])


def test_single_state_hot_path_equals_batched_lift() -> None:
    rng = np.random.default_rng(2)
    model = KoopmanModel.from_normalised(random_learned(rng), 0.025, NAMES_X, NAMES_U)
    states = rng.uniform([5, -1, -0.5], [25, 1, 0.5], (2, 5, 3))
    batched = model.lift(states)
    assert batched.shape == (2, 5, model.n_z)
    single = np.array([[model.lift(states[i, j]) for j in range(5)] for i in range(2)])
    print(f"max |single - batched| = {np.abs(single - batched).max():.2e}")
    np.testing.assert_allclose(single, batched, rtol=0, atol=1e-12)
    # The hot path reuses buffers: an earlier result must not change under a later call.
    first = model.lift(states[0, 0])
    kept = first.copy()
    model.lift(states[1, 1])
    assert np.array_equal(first, kept)


def test_predict_equals_repeated_step_lifted() -> None:
    rng = np.random.default_rng(3)
    model = KoopmanModel.from_normalised(random_learned(rng), 0.025, NAMES_X, NAMES_U)
    x0 = rng.uniform([5, -1, -0.5], [25, 1, 0.5], (3, 3))
    inputs = rng.uniform([-1000, -0.2], [2000, 0.2], (3, 10, 2))
    z = model.lift(x0)
    for k in range(10):
        z = model.step_lifted(z, inputs[:, k])
    err = np.abs(model.predict(x0, inputs)[:, -1] - z[:, :3]).max()
    print(f"max |predict - step_lifted x10| = {err:.2e}")
    assert err < 1e-9


def test_built_from_arrays_as_a_linear_model() -> None:
    A = np.array([[0.99, 0.0, 0.0], [0.0, 0.9, 0.02], [0.0, -0.05, 0.85]])
    B = np.array([[1e-4, 0.0], [0.0, 0.3], [0.0, 0.9]])
    model = KoopmanModel(A, B, None, [], 0.025, NAMES_X, NAMES_U)
    assert (model.n_x, model.n_u, model.n_z) == (3, 2, 3)
    x = np.array([10.0, 0.1, 0.2])
    np.testing.assert_array_equal(model.lift(x), x)
    np.testing.assert_allclose(model.predict(x[None], np.array([[[100.0, 0.05]]]))[0, 0], A @ x + B @ [100.0, 0.05])
    assert model.spectral_radius() == pytest.approx(max(abs(np.linalg.eigvals(A))))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"B": np.zeros((4, 2))}, "B must be"),
        ({"A": np.zeros((3, 4))}, "A must be square"),
        ({"offset": np.zeros(2)}, "offset must be"),
        ({"ts": 0.0}, "ts must be"),
        ({"encoder": [(np.zeros((4, 2)), np.zeros(4))]}, "encoder layer 0"),
        ({"A": np.full((3, 3), np.nan)}, "non-finite"),
    ],
)
def test_bad_definitions_are_refused_with_the_reason(kwargs: dict, message: str) -> None:
    args = {"A": np.eye(3), "B": np.zeros((3, 2)), "offset": None, "encoder": [], "ts": 0.025,
            "state_names": NAMES_X, "input_names": NAMES_U}
    args.update(kwargs)
    with pytest.raises(KoopmanError, match=message):
        KoopmanModel(**args)


def test_wrong_state_shapes_are_refused() -> None:
    model = KoopmanModel(np.eye(3), np.zeros((3, 2)), None, [], 0.025, NAMES_X, NAMES_U)
    with pytest.raises(KoopmanError, match=r"\(\.\.\., 3\)"):
        model.lift(np.zeros(2))
    with pytest.raises(KoopmanError, match="inputs of shape"):
        model.predict(np.zeros((2, 3)), np.zeros((2, 5, 3)))


def test_artifact_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    learned = random_learned(rng)
    save_artifact(tmp_path / "dk_test", learned, {"ts": 0.025, "state_names": list(NAMES_X),
                                                  "input_names": list(NAMES_U), "d": 4})
    model = KoopmanModel.load(tmp_path / "dk_test.npz")
    direct = KoopmanModel.from_normalised(learned, 0.025, NAMES_X, NAMES_U)
    for name in ("A", "B", "offset", "C_P"):
        np.testing.assert_array_equal(getattr(model, name), getattr(direct, name))
    assert model.metadata["d"] == 4 and model.state_names == NAMES_X


def test_missing_or_broken_artifacts_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(KoopmanError, match="not found"):
        KoopmanModel.load(tmp_path / "nothing.npz")
    rng = np.random.default_rng(5)
    save_artifact(tmp_path / "dk", random_learned(rng), {"ts": 0.025, "state_names": list(NAMES_X),
                                                         "input_names": list(NAMES_U)})
    meta = json.loads((tmp_path / "dk.json").read_text())
    del meta["state_min"]
    (tmp_path / "dk.json").write_text(json.dumps(meta))
    with pytest.raises(KoopmanError, match="dk.json: missing field 'state_min'"):
        KoopmanModel.load(tmp_path / "dk.npz")


def test_default_artifact_loads_and_is_stable() -> None:
    model = KoopmanModel.load()
    meta = model.metadata
    radius = model.spectral_radius()
    print(f"{DEFAULT_ARTIFACT.name}: d={meta['d']}, n_z={model.n_z}, spectral radius {radius:.4f}, "
          f"test errors {json.dumps(meta['test_errors'])}")
    assert model.n_u == 2 and model.n_z == model.n_x + len(model.dictionary) + meta["d"]
    # The vehicle states first; the default adds the measured wheel angle (the actuator's state).
    assert model.state_names == ("vx", "vy", "yaw_rate", "steer_measured") and model.input_names == ("torque", "steer")
    assert model.ts == 0.025
    # The largest radius over the scheduled form's knots; the end knots (3 and 35 m/s) see
    # the least data. A bound, not a tuned figure: 1.03^30 keeps a horizon's growth < 2.5.
    assert radius < 1.03
    for key in ("data_hash", "seed", "settings", "test_errors", "state_min", "input_max"):
        assert key in meta


def test_runtime_imports_never_pull_in_torch() -> None:
    code = ("import controller, firmware_sim, models.koopman, models.koopman_metrics, "
            "models.koopman_baselines, sys; assert 'torch' not in sys.modules, 'torch imported'")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.timing
def test_lift_time_of_one_state() -> None:
    """Benchmark: the controller lifts one state every 25 ms. Figure printed; generous bound."""
    model = KoopmanModel.load()
    x = np.array([12.0, 0.1, 0.05, 0.01])[: model.n_x]
    for _ in range(200):
        model.lift(x)
    samples = []
    for _ in range(20):
        t0 = time.perf_counter()
        for _ in range(200):
            model.lift(x)
        samples.append((time.perf_counter() - t0) / 200)
    median_us = float(np.median(samples)) * 1e6
    print(f"lift() of one state: median {median_us:.1f} us (min {min(samples) * 1e6:.1f} us)")
    assert median_us < 1000.0

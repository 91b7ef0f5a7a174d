"""ESO-DK predictor (models/eso_dk.py): Koopman model + held ESO disturbance estimate."""
from __future__ import annotations

import numpy as np
import pytest

from models.eso import EsoParams, EsoShapeError, design_gains
from models.eso_dk import EsoDkPredictor, rollout_lifted
from models.koopman import KoopmanModel

STATE_NAMES = ("vx", "vy", "yaw_rate")
INPUT_NAMES = ("torque", "steer")


def random_koopman(seed: int = 0, n_features: int = 3) -> KoopmanModel:
    """A KoopmanModel with a small random tanh encoder (stand-in for the trained artefact)."""
    rng = np.random.default_rng(seed)
    n_z = 3 + n_features
    encoder = [(0.3 * rng.standard_normal((8, 3)), 0.1 * rng.standard_normal(8)),
               (0.3 * rng.standard_normal((n_features, 8)), 0.1 * rng.standard_normal(n_features))]
    A = np.eye(n_z) + 0.02 * rng.standard_normal((n_z, n_z))
    A *= 0.99 / np.max(np.abs(np.linalg.eigvals(A)))
    B = 0.05 * rng.standard_normal((n_z, 2))
    offset = 0.01 * rng.standard_normal(n_z)
    return KoopmanModel(A, B, offset, encoder, 0.025, STATE_NAMES, INPUT_NAMES)


def linear_koopman(A: np.ndarray, B: np.ndarray, offset: np.ndarray) -> KoopmanModel:
    """No learned features: z = x, so a plant that is linear in x is exactly representable."""
    return KoopmanModel(A, B, offset, [], 0.025, STATE_NAMES, INPUT_NAMES)


def predictor_for(model: KoopmanModel, pole: float = 0.5) -> EsoDkPredictor:
    gains = design_gains(model.A, pole)
    return EsoDkPredictor(model, EsoParams(model.A, model.B, model.offset, gains.beta1, gains.beta2))


def test_rollout_without_disturbance_is_the_koopman_prediction() -> None:
    model = random_koopman()
    rng = np.random.default_rng(1)
    x0 = rng.standard_normal((4, 3))
    inputs = rng.standard_normal((4, 10, 2))
    ours = rollout_lifted(model, model.lift(x0), inputs) @ model.C_P.T
    reference = model.predict(x0, inputs)
    diff = float(np.max(np.abs(ours - reference)))
    print(f"DK rollout vs KoopmanModel.predict, max abs diff {diff:.3g}")
    assert diff < 1e-12


def test_held_disturbance_enters_every_step() -> None:
    model = random_koopman()
    predictor = predictor_for(model)
    rng = np.random.default_rng(2)
    x0 = rng.standard_normal(3)
    predictor.reset(x0)
    for _ in range(5):
        assert predictor.observe(rng.standard_normal(3), rng.standard_normal(2))
    w_hat = predictor.disturbance_estimate.copy()
    assert np.any(w_hat != 0)
    x = rng.standard_normal(3)
    inputs = rng.standard_normal((10, 2))
    z = model.lift(x)
    expected = []
    for u in inputs:  # eq. 15, written out independently
        z = model.A @ z + model.B @ u + model.offset + w_hat
        expected.append(z[:3])
    predicted = predictor.predict(x, inputs)
    diff = float(np.max(np.abs(predicted - np.array(expected))))
    print(f"10-step ESO-DK prediction vs hand recursion, max abs diff {diff:.3g}")
    assert diff < 1e-12
    assert np.max(np.abs(predictor.predict_one_step(x, inputs[0]) - predicted[0])) < 1e-12


def test_eso_removes_a_constant_model_error() -> None:
    """Plant = model + constant unknown force: after convergence ESO-DK predicts exactly, DK does not."""
    rng = np.random.default_rng(3)
    A = np.array([[0.999, 0.0, 0.0], [0.0, 0.95, -0.2], [0.0, 0.05, 0.9]])
    B = np.array([[1e-3, 0.0], [0.0, 0.3], [0.0, 0.8]])
    offset = np.array([0.0, 0.01, 0.0])
    model = linear_koopman(A, B, offset)
    model_error = np.array([-0.02, 0.015, -0.01])  # e.g. drag and a mu change the model never saw
    predictor = predictor_for(model, pole=0.5)
    inputs = np.column_stack([rng.uniform(-100, 100, 200), 0.05 * np.sin(np.arange(200) * 0.1)])
    x = np.array([11.1, 0.0, 0.0])
    states = [x]
    for u in inputs:
        x = A @ x + B @ u + offset + model_error
        states.append(x)
    k = 150
    predictor.reset(states[0])
    for i in range(k + 1):  # causal: the observer has seen x[0..k] and u[0..k]
        assert predictor.observe(states[i], inputs[i])
    horizon = inputs[k : k + 10]
    truth = np.array(states[k + 1 : k + 11])
    dk = rollout_lifted(model, model.lift(states[k])[None], horizon[None])[0] @ model.C_P.T
    dk_error = float(np.max(np.abs(dk - truth)))
    eso_error = float(np.max(np.abs(predictor.predict(states[k], horizon) - truth)))
    print(f"constant model error: 10-step max error DK {dk_error:.3g}, ESO-DK {eso_error:.3g}; "
          f"w_hat {np.round(predictor.disturbance_estimate, 6)}")
    assert eso_error < 1e-8
    assert dk_error > 0.05
    assert np.allclose(predictor.disturbance_estimate, model_error, atol=1e-9)


def test_non_finite_state_is_rejected() -> None:
    model = random_koopman()
    predictor = predictor_for(model)
    predictor.reset(np.zeros(3))
    assert predictor.observe(np.array([1.0, 0.1, 0.0]), np.zeros(2))
    before = predictor.disturbance_estimate.copy()
    assert predictor.observe(np.array([1.0, np.nan, 0.0]), np.zeros(2)) is False
    assert predictor.observe(np.array([1.0, 0.1, 0.0]), np.array([np.inf, 0.0])) is False
    assert np.array_equal(predictor.disturbance_estimate, before)
    print("NaN state and inf input rejected, estimate unchanged")


def test_observer_must_use_the_model_matrices() -> None:
    model = random_koopman()
    gains = design_gains(model.A, 0.5)
    with pytest.raises(EsoShapeError, match="offset differs"):
        EsoDkPredictor(model, EsoParams(model.A, model.B, model.offset + 1.0, gains.beta1, gains.beta2))
    with pytest.raises(EsoShapeError, match="inputs must be"):
        rollout_lifted(model, np.zeros((1, model.n_z)), np.zeros((1, 5, 3)))
    with pytest.raises(EsoShapeError, match="disturbance must be"):
        rollout_lifted(model, np.zeros((1, model.n_z)), np.zeros((1, 5, 2)), np.zeros(2))

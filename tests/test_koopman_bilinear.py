"""The bilinear lifted form with a dictionary: folding of the normalisation, I/O, speed dependence."""
from __future__ import annotations

import numpy as np
import pytest

from models.eso import design_gains, eso_update, initial_state
from models.eso_dk import observer_params, rollout_lifted
from models.koopman import DICTIONARY, KoopmanError, KoopmanModel, MinMaxScaling, dictionary_features, save_artifact
from test_koopman import NAMES_U, NAMES_X, random_learned

DICT = tuple(DICTIONARY)


def bilinear_learned(rng: np.random.Generator, n_features: int = 3):
    """A random bilinear model in normalised units with the full dictionary and a constant."""
    base = random_learned(rng, n_features)
    n_z = 3 + len(DICT) + n_features
    from dataclasses import replace
    return replace(
        base,
        A_n=np.eye(n_z) + rng.normal(0, 0.02, (n_z, n_z)),
        B_n=rng.normal(0, 0.05, (n_z, 2)),
        N_n=rng.normal(0, 0.05, (2, n_z, n_z)),
        affine_n=rng.normal(0, 0.01, n_z),
        dictionary=DICT,
        dictionary_scaling=MinMaxScaling(np.array([-0.2, -0.3, -10.0, 0.0]), np.array([0.2, 0.3, 10.0, 12.0])),
    )


def reference_predict(learned, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """Straight from the definition in normalised units -> physical states (batch, n, 3)."""
    sx, su, sd = learned.state_scaling, learned.input_scaling, learned.dictionary_scaling
    x_n = sx.normalise(x0)
    h = x_n
    for i, (w, b) in enumerate(learned.encoder):
        h = h @ w.T + b
        if i < len(learned.encoder) - 1:
            h = np.tanh(h)
    z_n = np.hstack([x_n, sd.normalise(dictionary_features(DICT, x0)), h])
    u_n = su.normalise(inputs)
    states = []
    for k in range(inputs.shape[1]):
        bilinear = np.einsum("bj,jac,bc->ba", u_n[:, k], learned.N_n, z_n)
        z_n = z_n @ learned.A_n.T + u_n[:, k] @ learned.B_n.T + learned.affine_n + bilinear
        states.append(z_n[:, :3] * (sx.high - sx.low) + sx.low)
    return np.stack(states, axis=1)


def test_physical_bilinear_matrices_match_the_normalised_model(tmp_path) -> None:
    rng = np.random.default_rng(3)
    learned = bilinear_learned(rng)
    model = KoopmanModel.from_normalised(learned, 0.025, NAMES_X, NAMES_U)
    assert model.form == "bilinear" and model.dictionary == DICT
    x0 = rng.uniform([5, -1, -0.5], [25, 1, 0.5], (8, 3))
    inputs = rng.uniform([-1000, -0.2], [2000, 0.2], (8, 30, 2))
    err = np.abs(model.predict(x0, inputs) - reference_predict(learned, x0, inputs)).max()
    print(f"max |predict - reference| over 30 steps = {err:.2e}")
    assert err < 1e-8
    # The run-time single-state lift equals the batched one (dictionary on scalars).
    assert np.allclose(model.lift(x0[0]), model.lift(x0[:1])[0], atol=1e-12)
    # Round trip through the artefact files.
    save_artifact(tmp_path / "bl", learned, {"ts": 0.025, "state_names": list(NAMES_X), "input_names": list(NAMES_U)})
    loaded = KoopmanModel.load(tmp_path / "bl.npz")
    assert loaded.form == "bilinear" and np.allclose(loaded.predict(x0, inputs), model.predict(x0, inputs))


def test_input_matrix_depends_on_the_state_only_for_the_bilinear_form() -> None:
    rng = np.random.default_rng(4)
    model = KoopmanModel.from_normalised(bilinear_learned(rng), 0.025, NAMES_X, NAMES_U)
    z_slow, z_fast = model.lift(np.array([10.0, 0.0, 0.0])), model.lift(np.array([25.0, 0.0, 0.0]))
    assert not np.allclose(model.input_matrix(z_slow), model.input_matrix(z_fast))
    # One step with B(z) equals the model's own bilinear step.
    u = np.array([300.0, 0.05])
    assert np.allclose(model.A @ z_slow + model.input_matrix(z_slow) @ u + model.offset,
                       model.step_lifted(z_slow, u))
    linear = KoopmanModel(np.eye(3), np.ones((3, 2)), None, [], 0.025, NAMES_X, NAMES_U)
    assert linear.form == "linear" and linear.input_matrix(np.zeros(3)) is linear.B


def test_observer_uses_the_input_matrix_at_the_measured_state() -> None:
    rng = np.random.default_rng(5)
    model = KoopmanModel.from_normalised(bilinear_learned(rng), 0.025, NAMES_X, NAMES_U)
    gains = design_gains(model.A, 0.5)
    params = observer_params(model, gains.beta1, gains.beta2)
    z = model.lift(np.array([15.0, 0.1, 0.05]))
    u = np.array([200.0, 0.03])
    state = eso_update(initial_state(z, params), z, u, params)  # no error: z_hat+ is the model's step
    assert np.allclose(state.lifted_state_estimate, model.step_lifted(z, u))
    assert np.allclose(rollout_lifted(model, z[None], u[None, None])[0, 0], model.step_lifted(z, u))


def test_a_dictionary_needs_the_vehicle_states_and_known_names() -> None:
    with pytest.raises(KoopmanError, match="unknown dictionary"):
        KoopmanModel(np.eye(4), np.zeros((4, 2)), None, [], 0.025, NAMES_X, NAMES_U, dictionary=("vx^3",))
    with pytest.raises(KoopmanError, match="needs the states"):
        KoopmanModel(np.eye(4), np.zeros((4, 2)), None, [], 0.025, ("a", "b", "c"), NAMES_U, dictionary=("r/vx",))

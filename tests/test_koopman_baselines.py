"""DMDc / EDMDc baselines and the Table I metrics (numpy only)."""
from __future__ import annotations

import numpy as np
import pytest

from models.koopman import KoopmanError
from models.koopman_baselines import DMDc, EDMDc
from models.koopman_metrics import Trajectory, open_loop_windows, prediction_errors

X = ("vx", "vy", "yaw_rate")
U = ("torque", "steer")
A_TRUE = np.array([[0.995, 0.0, 0.0], [0.0, 0.92, -0.2], [0.0, 0.03, 0.88]])
B_TRUE = np.array([[2e-5, 0.0], [0.0, 0.4], [0.0, 0.9]])
C_TRUE = np.array([-0.01, 0.0, 0.001])


def affine_runs(n_runs: int = 3, n: int = 300, seed: int = 0) -> list[Trajectory]:
    rng = np.random.default_rng(seed)
    runs = []
    for k in range(n_runs):
        u = np.column_stack([rng.uniform(-1000, 2000, n), rng.uniform(-0.1, 0.1, n)])
        x = np.empty((n, 3))
        x[0] = [rng.uniform(5, 20), 0.0, 0.0]
        for i in range(n - 1):
            x[i + 1] = A_TRUE @ x[i] + B_TRUE @ u[i] + C_TRUE
        runs.append(Trajectory(f"run{k}", x, u, X, U))
    return runs


def test_dmdc_recovers_an_affine_linear_system() -> None:
    model = DMDc(ridge=0.0).fit(affine_runs())
    err = max(np.abs(model.A_ - A_TRUE).max(), np.abs(model.B_ - B_TRUE).max(), np.abs(model.offset_ - C_TRUE).max())
    print(f"max |DMDc - true| over A, B, c: {err:.2e}")
    assert err < 1e-8


def test_dmdc_as_koopman_model_predicts_the_same() -> None:
    runs = affine_runs()
    dmdc = DMDc().fit(runs)
    model = dmdc.to_koopman_model(0.025)
    x0, inputs, _ = open_loop_windows(runs, 10, stride=50)
    np.testing.assert_allclose(model.predict(x0, inputs), dmdc.predict(x0, inputs), rtol=0, atol=1e-9)


def test_edmdc_fits_dynamics_linear_in_its_dictionary() -> None:
    """x1+ = 0.9 x1 + 0.05 x1^2 (in scaled units) is exactly representable with degree 2."""
    rng = np.random.default_rng(1)
    runs = []
    for k in range(3):
        n = 200
        x = np.empty((n, 3))
        x[0] = rng.uniform(0.1, 1.0, 3)
        u = rng.uniform(-1, 1, (n, 2))
        for i in range(n - 1):
            x[i + 1] = [0.9 * x[i, 0] + 0.05 * x[i, 0] ** 2 + 0.01 * u[i, 0], 0.8 * x[i, 1] + 0.1 * u[i, 1], 0.7 * x[i, 2]]
        runs.append(Trajectory(f"r{k}", x, u, X, U))
    edmdc = EDMDc(degree=2, ridge=0.0).fit(runs)
    dmdc = DMDc().fit(runs)
    e_edmd = prediction_errors(edmdc, runs, open_loop_steps=1, open_loop_stride=1)["vx"]["one_step_max"]
    e_dmd = prediction_errors(dmdc, runs, open_loop_steps=1, open_loop_stride=1)["vx"]["one_step_max"]
    print(f"one-step max error of x1: EDMDc {e_edmd:.2e}, DMDc {e_dmd:.2e}")
    assert e_edmd < 1e-8 < e_dmd


def test_baselines_refuse_bad_use() -> None:
    with pytest.raises(KoopmanError, match="not fitted"):
        DMDc().predict(np.zeros((1, 3)), np.zeros((1, 2, 2)))
    with pytest.raises(KoopmanError, match="degree must be >= 2"):
        EDMDc(degree=1)


def test_windows_never_cross_runs_and_a_perfect_predictor_scores_zero() -> None:
    runs = affine_runs(n_runs=2, n=50)
    x0, inputs, truth = open_loop_windows(runs, 40, stride=1)
    assert x0.shape == (2 * 10, 3) and inputs.shape == (20, 40, 2) and truth.shape == (20, 40, 3)
    np.testing.assert_array_equal(truth[10, -1], runs[1].states[40])

    class Exact:
        def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
            out, x = [], x0
            for i in range(inputs.shape[1]):
                x = x @ A_TRUE.T + inputs[:, i] @ B_TRUE.T + C_TRUE
                out.append(x)
            return np.stack(out, axis=1)

    errors = prediction_errors(Exact(), runs)
    worst = max(v for figures in errors.values() for v in figures.values())
    print(f"largest figure of the exact predictor: {worst:.1e}")
    assert worst < 1e-9
    with pytest.raises(KoopmanError, match="no run is longer than 60 steps"):
        open_loop_windows(runs, 60)

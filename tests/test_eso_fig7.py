"""Fig. 7 evaluation pieces (studies/fig7.py) on synthetic data: alignment and the metric."""
from __future__ import annotations

import numpy as np

from studies.fig7 import DriveSettings, drive_profile, observer_params, predict_along, prediction_rmse
from models.koopman import KoopmanModel

A = np.array([[0.999, 0.0, 0.0], [0.0, 0.95, -0.2], [0.0, 0.05, 0.9]])
B = np.array([[1e-4, 0.0], [0.0, 0.3], [0.0, 0.8]])
OFFSET = np.array([0.0, 0.0, 0.0])


def linear_model() -> KoopmanModel:
    return KoopmanModel(A, B, OFFSET, [], 0.025, ("vx", "vy", "yaw_rate"), ("torque", "steer"))


def drive(model_error: np.ndarray, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Linear plant = model + model_error (n_x,), steer sine, torque steps: states (n+1, 3), inputs (n, 2)."""
    t = np.arange(n) * 0.025
    inputs = np.column_stack([200.0 * np.sign(np.sin(0.5 * t)), 0.05 * np.sin(2 * np.pi * 0.4 * t)])
    states = np.empty((n + 1, 3))
    states[0] = [11.1, 0.0, 0.0]
    for k in range(n):
        states[k + 1] = A @ states[k] + B @ inputs[k] + OFFSET + model_error
    return states, inputs


def test_exact_model_predicts_exactly_and_windows_align() -> None:
    model = linear_model()
    states, inputs = drive(np.zeros(3))
    p = predict_along(model, observer_params(model, 0.5), states, inputs, horizon=10)
    errors = {name: float(np.max(np.abs(getattr(p, name) - ref)))
              for name, ref in (("one_step_dk", p.truth), ("one_step_eso", p.truth),
                                ("multi_dk", p.multi_truth), ("multi_eso", p.multi_truth))}
    print("exact model, max abs prediction errors:", {k: f"{v:.2g}" for k, v in errors.items()})
    assert p.multi_truth.shape == (len(inputs) - 9, 10, 3)
    assert np.array_equal(p.multi_truth[5, 3], states[5 + 4])
    assert max(errors.values()) < 1e-9


def test_eso_dk_beats_dk_with_a_model_error() -> None:
    model = linear_model()
    states, inputs = drive(np.array([-0.01, 0.01, -0.02]))
    r = prediction_rmse(predict_along(model, observer_params(model, 0.5), states, inputs, horizon=10))
    print(f"RMSE [vx, vy, r] 1-step DK {np.round(r['one_dk'], 4)} ESO-DK {np.round(r['one_eso'], 5)}; "
          f"10-step DK {np.round(r['multi_dk'], 4)} ESO-DK {np.round(r['multi_eso'], 5)}")
    assert np.all(r["one_eso"] < 0.2 * r["one_dk"])
    assert np.all(r["multi_eso"] < 0.2 * r["multi_dk"])


def test_drive_profile_is_deterministic_and_bounded() -> None:
    settings = DriveSettings()
    speed_a, steer_a = drive_profile(settings)
    speed_b, steer_b = drive_profile(settings)
    assert np.array_equal(steer_a, steer_b) and np.array_equal(speed_a, speed_b)
    assert steer_a.size == round(settings.duration_s / 0.025)
    assert np.max(np.abs(steer_a)) <= settings.max_steer
    assert speed_a[0] == settings.start_speed
    moving = np.mean(np.abs(steer_a) > 0.005)
    print(f"drive: {settings.duration_s} s, max |steer| {np.max(np.abs(steer_a)):.3f} rad, "
          f"steering active {100 * moving:.0f} % of the time, speed {3.6 * speed_a.min():.0f}-"
          f"{3.6 * speed_a.max():.0f} km/h")
    assert moving > 0.5

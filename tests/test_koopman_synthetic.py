"""A small synthetic nonlinear plant for the Koopman tests (no dependency on the real plant).

Single-track vehicle with saturating (tanh) tyres, state [vx, vy, yaw_rate], input
[torque, steer], Ts = 0.025 s, driven by smooth random inputs. Other Koopman test files
import ``synthetic_runs`` from here.
"""
from __future__ import annotations

import numpy as np

from models.koopman_metrics import Trajectory

TS = 0.025
STATES = ("vx", "vy", "yaw_rate")
INPUTS = ("torque", "steer")


def _derivatives(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """x (..., 3), u (..., 2) -> dx/dt (..., 3) of a tanh-tyre single-track model."""
    mass, inertia, lf, lr, radius = 1500.0, 2500.0, 1.2, 1.5, 0.3
    stiffness, force_max = 60000.0, 6500.0
    vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
    torque, steer = u[..., 0], u[..., 1]
    vx_safe = np.maximum(vx, 1.0)
    alpha_f = steer - (vy + lf * r) / vx_safe
    alpha_r = -(vy - lr * r) / vx_safe
    fy_f = force_max * np.tanh(stiffness * alpha_f / force_max)
    fy_r = force_max * np.tanh(stiffness * alpha_r / force_max)
    dvx = torque / (mass * radius) - 0.002 * vx**2 - fy_f * np.sin(steer) / mass + vy * r
    dvy = (fy_f * np.cos(steer) + fy_r) / mass - vx * r
    dr = (lf * fy_f * np.cos(steer) - lr * fy_r) / inertia
    return np.stack([dvx, dvy, dr], axis=-1)


def _smooth_signal(rng: np.random.Generator, n: int, amplitude: float, corr_steps: int) -> np.ndarray:
    knots = rng.uniform(-amplitude, amplitude, n // corr_steps + 2)
    return np.interp(np.arange(n) / corr_steps, np.arange(knots.size), knots)


def synthetic_runs(n_runs: int = 6, n_samples: int = 400, seed: int = 0) -> list[Trajectory]:
    """``n_runs`` trajectories of ``n_samples`` steps each at Ts = 0.025 s (RK4, 5 substeps)."""
    rng = np.random.default_rng(seed)
    runs = []
    for k in range(n_runs):
        torque = 300.0 + _smooth_signal(rng, n_samples, 900.0, 40)
        steer = _smooth_signal(rng, n_samples, 0.08, 20)
        inputs = np.stack([torque, steer], axis=1)
        states = np.empty((n_samples, 3))
        x = np.array([rng.uniform(8.0, 15.0), 0.0, 0.0])
        h = TS / 5
        for i in range(n_samples):
            states[i] = x
            u = inputs[i]
            for _ in range(5):
                k1 = _derivatives(x, u)
                k2 = _derivatives(x + h / 2 * k1, u)
                k3 = _derivatives(x + h / 2 * k2, u)
                k4 = _derivatives(x + h * k3, u)
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            # Keep the speed in a band, as a driver would.
            if x[0] > 20.0:
                inputs[i + 1 :, 0] = np.minimum(inputs[i + 1 :, 0], 0.0)
            elif x[0] < 6.0:
                inputs[i + 1 :, 0] = np.maximum(inputs[i + 1 :, 0], 600.0)
        runs.append(Trajectory(f"synthetic_{k:02d}", states, inputs, STATES, INPUTS))
    return runs


def test_synthetic_runs_are_nonlinear_and_bounded() -> None:
    runs = synthetic_runs(n_runs=3, n_samples=300)
    states = np.concatenate([r.states for r in runs])
    print(f"vx range {states[:, 0].min():.2f}..{states[:, 0].max():.2f} m/s, "
          f"|vy| max {np.abs(states[:, 1]).max():.3f} m/s, |r| max {np.abs(states[:, 2]).max():.3f} rad/s")
    assert np.all(np.isfinite(states))
    assert 4.0 < states[:, 0].min() and states[:, 0].max() < 25.0
    assert np.abs(states[:, 2]).max() > 0.05  # the steering excites the yaw dynamics

"""The plant's linearised modes fit inside RK4's stability region at the 1 ms step.

This is the verification the wheel-spin formulation (relaxed slip, models/vehicle.py)
needs: at every speed from standstill to 40 m/s, driving and braking, every eigenvalue
lambda of the Jacobian with Re(lambda) < 0 has |R(lambda h)| <= 1, where R is RK4's
amplification factor; and halving the step changes a standstill start by little.
"""
from __future__ import annotations

import numpy as np
import pytest

from models.vehicle import N_STATE, VX, PlantModel, VehicleBatch
from models.vehicle_params import load_vehicle_params


def _rk4_amplification(z: np.ndarray) -> np.ndarray:
    return np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)


def _jacobian(model: PlantModel, state: np.ndarray, steer: float, torque: float, mu: float) -> np.ndarray:
    eps = 1e-6
    jac = np.empty((N_STATE, N_STATE))
    args = (np.array([steer]), np.array([torque]), np.array([mu]))
    for j in range(N_STATE):
        plus, minus = state.copy(), state.copy()
        step = eps * max(1.0, abs(state[j]))
        plus[j] += step
        minus[j] -= step
        jac[:, j] = (model.derivatives(plus[None], *args)[0] - model.derivatives(minus[None], *args)[0]) / (2 * step)
    return jac


@pytest.mark.parametrize("speed", [0.0, 0.3, 1.0, 2.5, 5.0, 15.0, 40.0])
@pytest.mark.parametrize("torque", [0.0, 2000.0, -2000.0])
def test_modes_are_inside_rk4_stability_region_at_1ms(speed, torque):
    params = load_vehicle_params()
    model = PlantModel(params)
    batch = VehicleBatch(params, 1)
    batch.reset(np.array([speed]))
    # Let the actuators and slips settle a little at this operating point (keep the speed).
    for _ in range(20):
        batch.step(np.array([0.02]), np.array([torque]), 0.005)
        batch.state[0, VX] = speed
    eigen = np.linalg.eigvals(_jacobian(model, batch.state[0], 0.02, torque, params.mu))
    stable = eigen[eigen.real < 0]
    gain = _rk4_amplification(stable * params.integration_step)
    fastest = np.abs(stable).max()
    print(f"vx {speed:5.1f} m/s, T {torque:6.0f} N m: fastest mode |lambda| {fastest:8.1f} 1/s, "
          f"|lambda h| {fastest * params.integration_step:.3f}, max |R(lambda h)| {gain.max():.4f}")
    assert gain.max() <= 1.0 + 1e-9


def test_halving_the_step_changes_a_standstill_start_little():
    results = []
    for step in (0.001, 0.0005):
        params = load_vehicle_params(integration_step=step)
        batch = VehicleBatch(params, 1)
        batch.reset(np.array([0.0]))
        for _ in range(200):
            batch.step(np.array([0.1]), np.array([2500.0]), 0.005)
        results.append(batch.state[0].copy())
    diff = np.abs(results[0] - results[1])
    print(f"1 ms vs 0.5 ms after 1 s standstill start: max state difference {diff.max():.2e} "
          f"(vx {results[0][VX]:.4f} m/s)")
    assert diff[VX] < 1e-4 and diff.max() < 1e-3

"""The single-vehicle float path equals the vectorised plant derivative."""
from __future__ import annotations

import time

import dataclasses

import numpy as np
import pytest

from models.vehicle import N_STATE, FourWheelVehicle, PlantModel, ScalarPlant, VehicleBatch, VehicleCommand
from models.vehicle_params import load_vehicle_params


@pytest.mark.parametrize("rear_scale", [1.0, 0.8])
def test_scalar_derivative_equals_vectorised(rear_scale):
    # 0.8: the rear tyres' own cornering-stiffness factor reaches both implementations.
    params = dataclasses.replace(load_vehicle_params(), cornering_stiffness_rear_scale=rear_scale)
    model = PlantModel(params)
    scalar = ScalarPlant(model)
    rng = np.random.default_rng(0)
    states = model.initial_state(rng.uniform(0.0, 40.0, 200))
    states += rng.normal(0.0, 1.0, states.shape) * np.array(
        [1, 0.5, 0.3, 10, 10, 3, 5, 5, 5, 5, 0.05, 0.05, 0.05, 0.05, 0.1, 1000, 3, 3])
    steer = rng.uniform(-0.4, 0.4, 200)
    torque = rng.uniform(-4000, 4000, 200)
    mu = rng.uniform(0.3, 1.0, 200)
    batch = model.derivatives(states, steer, torque, mu)
    worst = 0.0
    for i in range(200):
        single = np.array(scalar.derivatives(states[i].tolist(), steer[i], torque[i], mu[i]))
        worst = max(worst, float(np.max(np.abs(single - batch[i]) / (1.0 + np.abs(batch[i])))))
    print(f"scalar vs vectorised derivative (rear stiffness x{rear_scale:g}): max relative "
          f"difference {worst:.2e} over 200 states")
    assert worst < 1e-9
    assert len(single) == N_STATE


def test_single_vehicle_trajectory_equals_batch_and_step_cost():
    params = load_vehicle_params()
    vehicle = FourWheelVehicle(params)
    batch = VehicleBatch(params, 1)
    vehicle.reset(vx=12.0)
    batch.reset(np.array([12.0]))
    single_cpu = 0.0
    for k in range(200):
        command = VehicleCommand(800.0 * np.sin(0.05 * k), 0.1 * np.sin(0.03 * k))
        started = time.process_time()
        vehicle.step(command, 0.005)
        single_cpu += time.process_time() - started
        batch.step(np.array([command.steer_angle]), np.array([command.drive_torque]), 0.005)
    diff = np.abs(vehicle.state - batch.state[0]).max()
    # A figure to report, not an assertion (timing depends on the machine).
    print(f"single vs batch after 1 s: max difference {diff:.2e}; FourWheelVehicle CPU time "
          f"per 5 ms step (five 1 ms RK4 steps) {1e3 * single_cpu / 200:.3f} ms")
    assert diff < 1e-8

"""Baseline models: linear bicycle against the plant, single track numpy vs CasADi."""
from __future__ import annotations

import numpy as np
import pytest

from models.bicycle import BicycleModelError, LinearBicycle, nominal_model_params
from models.single_track import NUMPY_OPS, single_track_derivatives, single_track_rk4_step
from models.tyre import tyre_forces
from models.vehicle import STEER, VX, VY, YAW_RATE, VehicleBatch
from models.vehicle_params import load_vehicle_params


def test_cornering_stiffness_is_the_tyre_slope_at_small_slip():
    params = load_vehicle_params()
    nominal = nominal_model_params(params)
    front_wheel_load = params.mass * params.gravity * params.lr / params.wheelbase / 2
    slip = np.array(0.002)  # 0.11 deg: linear range
    _, fy = tyre_forces(np.array(0.0), slip, np.array(front_wheel_load), params.mu, params)
    secant = 2 * float(fy) / float(slip)
    rel = abs(secant - nominal.cornering_stiffness_front) / nominal.cornering_stiffness_front
    print(f"front axle: identified {nominal.cornering_stiffness_front:.0f} N/rad, secant at 2 mrad "
          f"{secant:.0f} N/rad (rel. diff {rel:.1e}); rear {nominal.cornering_stiffness_rear:.0f} N/rad")
    assert rel < 1e-3


def test_linear_bicycle_matches_plant_yaw_rate_step_at_20_mps():
    params = load_vehicle_params()
    batch = VehicleBatch(params, 1)
    batch.reset(np.array([20.0]))
    step_angle = 0.005  # a_y ~ 0.6 m/s^2: linear range
    h = 0.005
    bicycle = LinearBicycle(nominal_model_params(params))
    ad, bd = bicycle.discrete_matrices(20.0, h)
    x_lin = np.zeros(2)
    plant_r, model_r = [], []
    for _ in range(int(3.0 / h)):
        # The bicycle gets the plant's actual wheel angle (its input is the wheel angle).
        wheel_angle = batch.state[0, STEER]
        torque = params.radius * params.mass * (20.0 - batch.state[0, VX]) + params.radius * 300.0
        batch.step(np.array([step_angle]), np.array([torque]), h)
        x_lin = ad @ x_lin + bd[:, 0] * wheel_angle
        plant_r.append(batch.state[0, YAW_RATE])
        model_r.append(x_lin[1])
    plant_r, model_r = np.array(plant_r), np.array(model_r)
    final = plant_r[-1]
    max_err = np.abs(plant_r - model_r).max() / abs(final)
    print(f"yaw-rate step at 20 m/s: plant steady {final:.5f} rad/s, bicycle {model_r[-1]:.5f}; "
          f"max error over 3 s {100 * max_err:.2f} % of the steady value")
    assert max_err < 0.05


def test_bicycle_rejects_non_positive_speed():
    with pytest.raises(BicycleModelError, match="vx"):
        LinearBicycle().continuous_matrices(0.0)


def test_single_track_numpy_and_casadi_agree_and_are_smooth():
    casadi = pytest.importorskip("casadi")
    from models.single_track import CASADI_OPS

    params = nominal_model_params()
    x = casadi.SX.sym("x", 3)
    steer = casadi.SX.sym("steer")
    torque = casadi.SX.sym("torque")
    expr = single_track_derivatives(x, steer, torque, params, CASADI_OPS)
    func = casadi.Function("f", [x, steer, torque], [expr, casadi.jacobian(expr, x)])
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(50):
        state = np.array([rng.uniform(0.0, 35.0), rng.normal(0, 1), rng.normal(0, 0.5)])
        d, t = rng.uniform(-0.3, 0.3), rng.uniform(-3000, 3000)
        value, jac = func(state, d, t)
        reference = single_track_derivatives(state, d, t, params, NUMPY_OPS)
        worst = max(worst, float(np.abs(np.array(value).ravel() - reference).max()))
        assert np.all(np.isfinite(np.array(jac)))
    print(f"single track numpy vs CasADi: max abs difference {worst:.2e}")
    assert worst < 1e-9


def test_single_track_steady_state_close_to_plant():
    params = load_vehicle_params()
    nominal = nominal_model_params(params)
    state = np.array([20.0, 0.0, 0.0])
    for _ in range(4000):   # 4 s at 1 ms, torque balancing the resistance
        resistance = nominal.drag_factor * 400 + nominal.rolling_resistance_force
        state = single_track_rk4_step(state, 0.01, resistance * nominal.wheel_radius, nominal, 0.001)
        state[0] = 20.0
    batch = VehicleBatch(params, 1)
    batch.reset(np.array([20.0]))
    for _ in range(160):
        torque = params.radius * params.mass * (20.0 - batch.state[0, VX]) + params.radius * 300.0
        batch.step(np.array([0.01]), np.array([torque]), 0.025)
    rel = abs(state[2] - batch.state[0, YAW_RATE]) / abs(batch.state[0, YAW_RATE])
    print(f"steady yaw rate at 20 m/s, 0.01 rad: single track {state[2]:.5f}, plant "
          f"{batch.state[0, YAW_RATE]:.5f} rad/s (rel. diff {100 * rel:.2f} %)")
    assert rel < 0.05
    assert abs(state[1] - batch.state[0, VY]) < 0.05

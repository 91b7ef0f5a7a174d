"""Four-wheel plant: handling figures, braking, symmetry, coasting, standstill, robustness."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.bicycle import nominal_model_params
from studies.handling import steady_state
from models.errors import VehicleCommandError, VehicleParamsError
from models.vehicle import (ACCEL_Y_FILT, POS_Y, STEER, VX, VY, YAW, YAW_RATE, FourWheelVehicle,
                            VehicleBatch, VehicleCommand)
from models.vehicle_params import load_vehicle_params

TS = 0.025


@pytest.fixture(scope="module")
def steady_states() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Steady cornering at 20 m/s, (steer, state, steady mask) per case, in one batch:
    small steer (linear range) at mu 0.85, and steer around the limit for mu 0.85 and 0.5."""
    params = load_vehicle_params()
    cases = {"linear": (0.85, np.linspace(0.004, 0.02, 5)),
             "limit 0.85": (0.85, np.linspace(0.08, 0.14, 7)),
             "limit 0.5": (0.5, np.linspace(0.04, 0.10, 7))}
    steer = np.concatenate([s for _, s in cases.values()])
    mu = np.concatenate([np.full(s.size, m) for m, s in cases.values()])
    state, steady = steady_state(params, mu, np.full(steer.size, 20.0), steer, seconds=6.0)
    out, start = {}, 0
    for name, (_, s) in cases.items():
        rows = slice(start, start + s.size)
        out[name] = (steer[rows], state[rows], steady[rows])
        start += s.size
    return out


def test_steady_state_cornering_understeers_at_20_mps(steady_states):
    steer, state, steady = steady_states["linear"]
    assert steady.all()
    linear = slice(None)
    ay = state[linear, ACCEL_Y_FILT]
    wheelbase = load_vehicle_params().wheelbase
    # delta = L r / vx + K_us a_y: the slope of (delta - L r/vx) against a_y is K_us.
    excess = steer[linear] - wheelbase * state[linear, YAW_RATE] / state[linear, VX]
    k_plant = np.polyfit(ay, excess, 1)[0]
    k_nominal = nominal_model_params().understeer_gradient
    print(f"understeer gradient at 20 m/s: plant {k_plant:.5f} rad/(m/s^2), "
          f"static-load bicycle {k_nominal:.5f}; a_y up to {ay.max():.2f} m/s^2")
    assert k_plant > 0.0
    # Load transfer only adds understeer on top of the static-load value.
    assert k_nominal * 0.9 < k_plant < k_nominal * 2.0


@pytest.mark.parametrize("mu", [0.85, 0.5])
def test_peak_lateral_acceleration_is_near_mu_g(steady_states, mu):
    _, state, steady = steady_states[f"limit {mu}"]
    peak = np.max(np.abs(state[steady, ACCEL_Y_FILT]))
    mu_g = mu * 9.81
    print(f"mu {mu}: peak steady a_y {peak:.3f} m/s^2 = {peak / mu_g:.3f} mu g "
          f"({steady.sum()} of {steady.size} points steady)")
    assert abs(peak - mu_g) < 0.1 * mu_g


@pytest.mark.parametrize("mu,brake_torque", [(0.85, 3200.0), (0.5, 3200.0), (0.85, 9000.0)])
def test_straight_line_braking_is_bounded_by_mu_g(mu, brake_torque):
    params = load_vehicle_params(mu=mu, max_brake_torque=brake_torque)
    vehicle = FourWheelVehicle(params)
    vehicle.reset(vx=25.0)
    speeds = [25.0]
    for _ in range(int(2.0 / TS)):
        speeds.append(vehicle.step(VehicleCommand(-brake_torque, 0.0), TS).vx)
    decel = -np.diff(speeds) / TS
    resistance = (0.5 * params.air_density * params.drag_coefficient * params.frontal_area * 25.0 ** 2
                  + params.rolling_resistance * params.mass * params.gravity) / params.mass
    bound = mu * params.gravity + resistance
    print(f"mu {mu}, brake {brake_torque:.0f} N m: max deceleration {decel.max():.3f} m/s^2, "
          f"bound mu g + resistance {bound:.3f}")
    assert decel.max() <= bound * 1.01
    assert decel[-10:].mean() > 0.5 * min(mu * params.gravity, brake_torque / params.radius / params.mass)


def test_left_right_symmetry():
    params = load_vehicle_params()
    batch = VehicleBatch(params, 2)
    batch.reset(np.array([15.0, 15.0]))
    for k in range(120):
        steer = 0.05 * np.sin(2 * np.pi * 0.8 * k * TS) * np.array([1.0, -1.0])
        batch.step(steer, np.array([400.0, 400.0]), TS)
    left, right = batch.state
    mirrored = np.array([VY, YAW_RATE, POS_Y, YAW, STEER])
    diff = np.max(np.abs(left[mirrored] + right[mirrored]))
    same = np.max(np.abs(left[[VX]] - right[[VX]]))
    print(f"left/right mirror error: lateral {diff:.2e}, longitudinal {same:.2e}")
    assert diff < 1e-9 and same < 1e-9
    assert abs(left[YAW_RATE]) > 0.01


def test_coasting_loses_speed_monotonically():
    vehicle = FourWheelVehicle()
    vehicle.reset(vx=30.0)
    speeds = [vehicle.step(VehicleCommand(0.0, 0.0), 0.1).vx for _ in range(150)]
    steps = np.diff(speeds)
    print(f"coasting 15 s from 30 m/s: {speeds[-1]:.2f} m/s, largest speed step {steps.max():.2e}")
    assert np.all(steps < 0.0)
    assert 20.0 < speeds[-1] < 29.0


def test_standstill_start_and_stop_without_nan_or_chatter():
    vehicle = FourWheelVehicle()
    vehicle.reset(vx=0.0)
    for _ in range(40):                       # at rest, no command: stays at rest
        out = vehicle.step(VehicleCommand(0.0, 0.0), 0.005)
    assert abs(out.vx) < 1e-9 and abs(out.yaw_rate) < 1e-9
    for _ in range(400):                      # full drive torque, steered, from standstill
        out = vehicle.step(VehicleCommand(3000.0, 0.2), 0.005)
    assert out.vx > 3.0 and out.yaw_rate > 0.0
    for _ in range(1200):                     # full braking to standstill
        out = vehicle.step(VehicleCommand(-3200.0, 0.2), 0.005)
    tail = []
    for _ in range(200):
        out = vehicle.step(VehicleCommand(-3200.0, 0.2), 0.005)
        tail.append((out.vx, out.vy, out.yaw_rate, *vehicle.diagnostics().wheel_speed))
    tail = np.array(tail)
    print(f"after stopping: max |vx| {np.abs(tail[:, 0]).max():.2e} m/s, max |vy| "
          f"{np.abs(tail[:, 1]).max():.2e}, max |wheel speed| {np.abs(tail[:, 3:]).max():.2e} rad/s")
    assert np.all(np.isfinite(tail))
    assert np.abs(tail[:, 0]).max() < 0.01 and np.abs(tail[:, 3:]).max() < 0.05
    assert np.all(tail[:, 0] > -1e-6)  # braking never reverses the car


def test_plant_carries_the_can_signals_and_diagnostics():
    vehicle = FourWheelVehicle(mass=1848.0, mu=0.55)
    assert vehicle.params.mass == 1848.0 and vehicle.mu == 0.55
    vehicle.reset(vx=10.0, x=5.0, y=-2.0, yaw=3.1)
    for _ in range(200):
        out = vehicle.step(VehicleCommand(500.0, 0.5), 0.005)  # beyond the 0.3 rad limit
    assert out.steer_angle == pytest.approx(0.3, abs=1e-6)
    assert out.drive_torque == pytest.approx(500.0, rel=1e-6)
    assert -np.pi <= out.yaw < np.pi
    diag = vehicle.diagnostics()
    for field in dataclasses.fields(diag):
        assert getattr(diag, field.name).shape == (4,)
    assert np.all(diag.normal_load > 0)
    vehicle.set_friction(0.3)
    assert vehicle.mu == 0.3


def test_bad_inputs_raise_typed_errors():
    vehicle = FourWheelVehicle()
    with pytest.raises(VehicleCommandError, match="command"):
        vehicle.step(VehicleCommand(float("nan"), 0.0), 0.005)
    with pytest.raises(VehicleCommandError, match="dt"):
        vehicle.step(VehicleCommand(0.0, 0.0), 0.0)
    with pytest.raises(VehicleCommandError, match="mu"):
        vehicle.set_friction(-1.0)
    with pytest.raises(VehicleParamsError, match="mass"):
        load_vehicle_params(mass=-5.0)
    with pytest.raises(VehicleParamsError, match="wheel_count"):
        load_vehicle_params(wheel_count=4.0)


@pytest.mark.slow
def test_ten_minute_random_drive_stays_finite_and_bounded():
    """20 vehicles x 30 s = 10 minutes of random driving, with stops and restarts."""
    params = load_vehicle_params()
    rng = np.random.default_rng(1)
    n = 20
    batch = VehicleBatch(params, n)
    batch.reset(rng.uniform(0.0, 30.0, n))
    steer = np.zeros(n)
    torque = np.zeros(n)
    worst = 0.0
    for k in range(int(30.0 / TS)):
        if k % 40 == 0:
            torque = rng.choice([-3200.0, -800.0, 0.0, 800.0, 3200.0], n)
        steer = np.clip(steer + rng.normal(0.0, 0.02, n), -0.35, 0.35)
        state = batch.step(steer, torque, TS)
        assert np.all(np.isfinite(state)), f"non-finite state at t = {k * TS:.3f} s"
        worst = max(worst, np.abs(state[:, VX]).max())
    print(f"10 min random drive: max |vx| {worst:.2f} m/s, all finite")
    assert worst < 60.0

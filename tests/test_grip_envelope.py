"""The grip envelope (controller/grip_envelope.py): the estimate on hand-made samples, the
QP's yaw-rate rows it narrows, and a spinning car it keeps on the road (the tuning fields' ranges
and both ECUs' verdicts on them: tests/test_firmware_c_actuator.py)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.base import VehicleSample
from controller.grip_envelope import MAX_GRIP_M_S2, MIN_GRIP_M_S2, MIN_SPEED_M_S, GripEnvelope, RearAxle
from controller.steering_qp import SteeringQp
from controller.tuning import load_tuning
from tests.tuning_helpers import controller_with

TS = 0.025
#: A round-number rear axle: m lf / L / Cr = 1500 * 1.2 / 2.8 / 100000 rad per m/s^2.
AXLE = RearAxle(mass=1500.0, lf=1.2, lr=1.6, cornering_stiffness_rear=100_000.0)
THRESHOLD = math.radians(3.0)


#: The envelope's fields of these hand-made cases (whatever the tuning file's are).
FIELDS = {"grip_slip_excess": THRESHOLD, "grip_margin": 0.1, "grip_recovery": 10.0, "grip_peak_time": 1.0}


def envelope(**fields: float) -> GripEnvelope:
    table = dataclasses.replace(load_tuning().for_controller("dkmpc"), **{**FIELDS, **fields})
    return GripEnvelope(table, AXLE, TS)


def sample(vx: float, vy: float, yaw_rate: float) -> VehicleSample:
    return VehicleSample(vx, vy, yaw_rate, 0.0, 0.0, 0.0, 0.0, 0.0, vx)


def steady_turn(vx: float, lateral_accel: float, extra_rear_slip: float = 0.0) -> VehicleSample:
    """A steady turn (vy constant) at ``lateral_accel`` whose rear slip angle is the linear
    tyre's plus ``extra_rear_slip`` (rad): vy from alpha = (lr r - vy) / vx."""
    yaw_rate = lateral_accel / vx
    rear_slip = AXLE.linear_slip(lateral_accel) + math.copysign(extra_rear_slip, lateral_accel)
    return sample(vx, AXLE.lr * yaw_rate - rear_slip * vx, yaw_rate)


def hold(grip: GripEnvelope, turn: VehicleSample) -> float:
    """``grip.update`` with the previous vy equal to the sample's: a steady turn (vy' = 0),
    whatever the sample before it was."""
    grip.previous_vy = turn.vy
    return grip.update(turn)


def test_the_lateral_acceleration_includes_the_lateral_velocity_change() -> None:
    grip = envelope()
    grip.update(sample(15.0, 0.0, 0.2))
    grip.update(sample(15.0, 0.05, 0.2))  # a_y = 0.05 / Ts + 0.2 * 15 = 5 m/s^2
    assert grip.peak == pytest.approx(5.0)


def test_a_linear_tyre_in_a_steady_turn_gives_no_bound() -> None:
    grip = envelope()
    assert grip.update(steady_turn(20.0, 6.0)) == math.inf  # the first sample has no previous vy
    for _ in range(10):
        bound = grip.update(steady_turn(20.0, 6.0))
    print("bound", bound, "grip", grip.grip, "sliding", grip.sliding)
    assert not grip.sliding
    assert grip.grip == MAX_GRIP_M_S2
    # At the ceiling (no evidence of a limit) no bound at all: the QP is the one with it off.
    assert bound == math.inf


def test_a_sliding_rear_axle_sets_the_grip_to_the_recent_peak_and_the_bound_follows() -> None:
    grip = envelope()
    for accel in (2.0, 3.0, 4.5):  # building up, linear tyre
        hold(grip, steady_turn(15.0, accel))
    bound = hold(grip, steady_turn(15.0, 4.0, extra_rear_slip=THRESHOLD + 0.01))
    decay = math.exp(-TS / 1.0)
    print("bound", bound, "grip", grip.grip, "peak", grip.peak)
    assert grip.sliding
    # The recent peak of |a_y| (4.5 m/s^2 one step back, decayed), not the 4.0 of the sliding sample.
    assert grip.grip == pytest.approx(4.5 * decay, rel=1e-9)
    assert bound == pytest.approx(1.1 * grip.grip / 15.0)
    # Just below the threshold: not sliding, and the estimate recovers by recovery * Ts.
    before = grip.grip
    hold(grip, steady_turn(15.0, 4.0, extra_rear_slip=THRESHOLD - 0.005))
    assert not grip.sliding
    assert grip.grip == pytest.approx(before + 10.0 * TS)


def test_the_estimate_returns_to_no_bound_at_the_recovery_rate_and_never_below_its_floor() -> None:
    grip = envelope(grip_recovery=20.0)
    hold(grip, steady_turn(15.0, 0.5, extra_rear_slip=0.2))  # sliding at a tiny a_y
    assert grip.sliding and grip.grip == MIN_GRIP_M_S2
    steps = math.ceil((MAX_GRIP_M_S2 - MIN_GRIP_M_S2) / (20.0 * TS))
    for step in range(steps):
        bound = hold(grip, steady_turn(15.0, 0.5))
        assert grip.grip == pytest.approx(min(MIN_GRIP_M_S2 + (step + 1) * 20.0 * TS, MAX_GRIP_M_S2))
        assert (bound == math.inf) == (grip.grip == MAX_GRIP_M_S2)
    assert grip.grip == MAX_GRIP_M_S2


def test_off_slow_and_reset_give_no_bound() -> None:
    off = GripEnvelope(dataclasses.replace(load_tuning().for_controller("dkmpc"), grip_slip_excess=0.0), AXLE, TS)
    assert not off.enabled
    assert hold(off, steady_turn(15.0, 4.0, extra_rear_slip=0.2)) == math.inf
    grip = envelope()
    assert hold(grip, steady_turn(MIN_SPEED_M_S - 0.5, 1.0, extra_rear_slip=0.2)) == math.inf
    assert not grip.sliding
    hold(grip, steady_turn(15.0, 4.0, extra_rear_slip=0.2))
    assert grip.sliding and grip.grip < MAX_GRIP_M_S2
    grip.reset()
    assert grip.grip == MAX_GRIP_M_S2 and grip.previous_vy is None and grip.peak == 0.0


def test_the_nominal_rear_axle_is_the_bicycle_of_lmpc() -> None:
    from models.bicycle import nominal_model_params

    nominal, params = RearAxle.nominal(), nominal_model_params()
    assert (nominal.mass, nominal.lf, nominal.lr, nominal.cornering_stiffness_rear) == (
        params.mass, params.lf, params.lr, params.cornering_stiffness_rear)


def test_the_bound_narrows_only_the_yaw_rate_rows_of_the_qp() -> None:
    table = load_tuning().for_controller("dkmpc")
    n_pred, n_ctrl = table.prediction_horizon, table.control_horizon
    qp = SteeringQp(table)
    free = np.tile([15.0, 0.1, 0.2], (n_pred, 1))
    args = (np.zeros((n_pred, 3, n_ctrl)), np.zeros((n_pred, 3)), 0.0, np.zeros((n_pred, 3, n_ctrl)), free,
            np.zeros(n_ctrl))
    qp.solve(*args)
    upper, lower = qp._soft_upper.copy(), qp._soft_lower.copy()
    qp.solve(*args, yaw_rate_bound=0.3)
    yaw = qp._yaw_rows
    print("yaw rows", int(yaw.sum()), "of", yaw.size)
    assert yaw.any() and not yaw.all()
    assert np.array_equal(qp._soft_upper[~yaw], upper[~yaw]) and np.array_equal(qp._soft_lower[~yaw], lower[~yaw])
    assert np.allclose(qp._soft_upper[yaw], 0.3 - 0.2) and np.allclose(qp._soft_lower[yaw], -0.3 - 0.2)
    # A bound wider than the table's keeps the table's.
    qp.solve(*args, yaw_rate_bound=5.0)
    assert np.array_equal(qp._soft_upper, upper) and np.array_equal(qp._soft_lower, lower)


def test_dkmpc_with_the_envelope_keeps_the_changed_plant_on_the_low_mu_lane_change() -> None:
    """make identify's changed plant (mass +300 kg, rear tyres x0.8, steering lag x3) spins
    on Table III's lane change with the nominal models; with the envelope on, DKMPC drives it
    through (a property of the envelope, not a ranking: no other controller is run)."""
    from hil.scenario import load_scenario
    from models.vehicle import VehicleCommand
    from studies.closed_loop import run_closed_loop
    from studies.identification import changed_params

    scenario = load_scenario("dlc_low_mu")
    plant = scenario.vehicle(changed_params(scenario.vehicle_params()))
    controller = controller_with("dkmpc", grip_slip_excess=THRESHOLD)
    result = run_closed_loop(scenario, controller, plant=plant, command_type=VehicleCommand)
    worst = float(np.max(np.abs(result.trace.lateral_error)))
    print("completed", result.completed, "e_Y RMSE", result.tracking.lateral.rmse, "max", worst,
          "grip at the end", controller.grip.grip)
    assert result.completed
    assert worst < 1.0
    assert result.steer_limit_held


def test_nmpc_narrows_its_soft_yaw_rate_rows_and_only_them() -> None:
    from controller.nmpc import Nmpc

    nmpc = controller_with("nmpc", grip_slip_excess=THRESHOLD)
    assert isinstance(nmpc, Nmpc) and nmpc.grip is not None
    table = nmpc.tuning
    lower, upper = nmpc.constraint_bounds(math.inf)
    assert lower is nmpc._lower_g and upper is nmpc._upper_g
    narrow_lower, narrow_upper = nmpc.constraint_bounds(0.3)
    changed = (narrow_lower != lower) | (narrow_upper != upper)
    n_equal = nmpc._n_states
    assert not changed[:n_equal].any()
    # One upper row (x - s <= 0.3) and one lower row (x + s >= -0.3) per step, the yaw rate's.
    assert changed.sum() == 2 * table.prediction_horizon
    soft_upper = narrow_upper[n_equal:].reshape(table.prediction_horizon, 2, 3)
    soft_lower = narrow_lower[n_equal:].reshape(table.prediction_horizon, 2, 3)
    assert np.all(soft_upper[:, 0, 2] == 0.3) and np.all(soft_lower[:, 1, 2] == -0.3)
    # Wider than the table's: the table's.
    wide_lower, wide_upper = nmpc.constraint_bounds(5.0)
    assert np.array_equal(wide_lower, lower) and np.array_equal(wide_upper, upper)

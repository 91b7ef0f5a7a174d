"""The heading target's side slip (controller/steady_slip.py): the measured slip, the
reference's bend, the bound and the fade, and every MPC's heading target moved by it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controller.base import STEER_LIMIT_RAD, VehicleSample
from controller.reference import ReferencePath
from controller.registry import MPC_NAMES
from controller.steady_slip import SLIP_MIN_SPEED, measured_slip, reference_bend, slip_target
from tuning_helpers import controller_with


def test_the_measured_slip_is_vy_over_vx_with_a_floor_on_the_speed() -> None:
    assert measured_slip(0.14, 14.0) == pytest.approx(0.01)
    assert measured_slip(-0.2, 0.0) == -0.2 / SLIP_MIN_SPEED
    assert measured_slip(0.1, -3.0) == 0.1 / SLIP_MIN_SPEED


@pytest.mark.parametrize("name", MPC_NAMES)
def test_every_mpc_moves_its_heading_target_by_the_measured_slip_on_a_straight(name: str) -> None:
    """With the target on, a sample crabbing on a straight (vy 0.14 m/s at 14 m/s) moves
    the heading target by 0.01 rad; with it off (limit 0), not at all."""
    x = np.linspace(0.0, 200.0, 401)
    path = ReferencePath.from_arrays(x, np.zeros_like(x), np.zeros_like(x))
    sample = VehicleSample(vx=14.0, vy=0.14, yaw_rate=0.0, x=10.0, y=0.0, yaw=0.0, steer_angle=0.0,
                           drive_torque=0.0, target_speed=14.0)
    for limit, expected in ((0.02, 0.01), (0.0, 0.0)):
        controller = controller_with(name, slip_target_limit=limit, slip_target_gate=0.003)
        controller.set_path(path)
        command, _ = controller.step(sample)
        assert controller.slip_target == pytest.approx(expected, abs=1e-12)
        assert abs(command.steer_angle) <= STEER_LIMIT_RAD


def test_the_bend_is_zero_on_a_straight_and_an_arc_and_grows_in_a_lane_change() -> None:
    steps = np.arange(30)
    assert reference_bend(np.full(30, 0.3)) == 0.0
    assert reference_bend(0.3 + 0.004 * steps) == pytest.approx(0.0, abs=1e-12)
    # an arc across the +-pi wrap is still an arc
    assert reference_bend(np.remainder(math.pi - 0.05 + 0.004 * steps + math.pi, 2 * math.pi) - math.pi) \
        == pytest.approx(0.0, abs=1e-9)
    lane_change = 0.05 * np.sin(np.pi * steps / 29)
    assert reference_bend(lane_change) == pytest.approx(0.05, rel=1e-2)


def test_the_target_is_bounded_faded_and_off_at_limit_zero() -> None:
    assert slip_target(0.005, 0.0, 0.02, 0.01) == 0.005
    assert slip_target(-0.05, 0.0, 0.02, 0.01) == -0.02
    assert slip_target(0.005, 0.005, 0.02, 0.01) == pytest.approx(0.0025)
    assert slip_target(0.005, 0.02, 0.02, 0.01) == 0.0
    assert slip_target(0.005, 0.0, 0.0, 0.01) == 0.0
    assert slip_target(math.nan, 0.0, 0.02, 0.01) == 0.0

"""Delay compensation (issue 37, controller/delay_compensation.py): the window's arithmetic,
and the moved prediction of each QP MPC against its own affine prediction.

A delay of exactly one step Ts with the previous command in flight must start the horizon
where the unmoved prediction is one step later under that command: for a model linear in
its start state, free_d[i] + gain[i] @ U == free[i + 1] + gain[i + 1] @ [u_prev, U_0, ...]
(the held last input aside). That ties the forward step of each controller's own model
(``shift_start``) to the prediction the QP already uses.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.base import VehicleSample
from controller.delay_compensation import (COMMAND_HISTORY, DelayWindow, delay_window, forward_state, pose_after,
                                           total_delay)
from controller.dkmpc import Dkmpc
from controller.eso_dkmpc import EsoDkmpc
from controller.lmpc import Lmpc
from controller.reference import ReferencePath
from controller.tuning import load_tuning
from models.bicycle import LinearBicycle
from models.koopman import KoopmanModel

TS = 0.025


def test_total_delay_is_off_without_the_fixed_part() -> None:
    assert total_delay(0.0, 0.008) == 0.0
    assert total_delay(0.02, 0.005) == pytest.approx(0.025)
    assert total_delay(0.02, math.nan) == 0.02 and total_delay(0.02, -1.0) == 0.02


def test_delay_window_splits_steps_and_picks_the_commands_in_flight() -> None:
    history = [0.01, 0.02, 0.03]  # oldest first
    window = delay_window(0.035, TS, history)
    assert window.whole_steps == 1 and window.fraction == pytest.approx(0.4)
    np.testing.assert_array_equal(window.inputs, [0.02, 0.03])  # the newest acts last
    short = delay_window(0.06, TS, [0.05])
    np.testing.assert_array_equal(short.inputs, [0.05, 0.05, 0.05])  # the oldest stands in
    assert delay_window(10.0, TS, history).whole_steps == COMMAND_HISTORY - 1


def test_forward_state_interpolates_the_last_step() -> None:
    window = DelayWindow(1, 0.5, np.array([1.0, 2.0]))
    moved = forward_state(lambda x, u: x + u, np.array([0.0]), window)
    assert moved[0] == pytest.approx(1.0 + 0.5 * 2.0)


def test_pose_after_follows_the_velocities() -> None:
    window = DelayWindow(0, 0.4, np.array([0.0]))
    pose = pose_after(np.array([1.0, 2.0, 0.0]), np.array([[10.0, 0.5, 0.2]]), TS, window)
    np.testing.assert_allclose(pose, [1.0 + 0.01 * 10.0, 2.0 + 0.01 * 0.5, 0.01 * 0.2])
    midpoint = pose_after(np.array([1.0, 2.0, 0.0]), np.array([[10.0, 0.5, 0.2]]), TS, window, 0.5)
    heading = 0.005 * 0.2  # half of the 0.01 s step's turn
    np.testing.assert_allclose(midpoint, [1.0 + 0.01 * (10.0 * np.cos(heading) - 0.5 * np.sin(heading)),
                                          2.0 + 0.01 * (10.0 * np.sin(heading) + 0.5 * np.cos(heading)), 0.01 * 0.2])


def test_pose_after_agrees_with_the_horizon_rollout() -> None:
    """Whole steps: the same poses as the horizon's rollout with either heading advance."""
    from controller.pose_kinematics import rollout_pose

    states = np.column_stack((np.linspace(12.0, 14.0, 5), np.linspace(-0.2, 0.3, 5), np.linspace(0.1, 0.4, 5)))
    pose0 = np.array([3.0, -1.0, 0.7])
    for advance in (0.0, 0.5):
        rollout = rollout_pose(pose0, states[:4], TS, advance)
        window = DelayWindow(4, 0.0, np.zeros(5))
        np.testing.assert_allclose(pose_after(pose0, states, TS, window, advance), rollout[-1], rtol=0, atol=1e-12)


def _controllers() -> dict[str, object]:
    tuning = load_tuning()
    model = KoopmanModel.load()
    return {"eso-dkmpc": lambda t: EsoDkmpc(model, t, tuning.longitudinal),
            "dkmpc": lambda t: Dkmpc(model, t, tuning.longitudinal),
            "lmpc": lambda t: Lmpc(LinearBicycle(), t, tuning.longitudinal)}


@pytest.mark.parametrize("name", ["eso-dkmpc", "dkmpc", "lmpc"])
def test_one_step_of_delay_starts_the_horizon_one_step_later(name: str) -> None:
    tuning = load_tuning().for_controller(name)
    controller = _controllers()[name](dataclasses.replace(tuning, delay_compensation_s=TS))
    sample = VehicleSample(vx=15.0, vy=0.1, yaw_rate=0.05, x=0.0, y=0.0, yaw=0.0, steer_angle=0.01,
                           drive_torque=100.0, target_speed=15.0)
    u_prev = 0.02
    torque = 50.0
    free, gain = controller.predict_states(sample, torque)
    window = DelayWindow(1, 0.0, np.array([u_prev, u_prev]))
    moved = controller.shift_start(free, window)
    n_ctrl = tuning.control_horizon
    steer = np.linspace(0.01, 0.03, n_ctrl)
    with_previous = np.concatenate(([u_prev], steer[:-1]))  # U shifted one step behind u_prev
    # Steps before the held last input reaches the compared step: i + 1 < n_ctrl.
    for i in range(n_ctrl - 1):
        later = free[i + 1] + gain[i + 1] @ with_previous
        print(name, i, np.max(np.abs(moved[i] + gain[i] @ steer - later)))
        np.testing.assert_allclose(moved[i] + gain[i] @ steer, later, rtol=0, atol=1e-9)

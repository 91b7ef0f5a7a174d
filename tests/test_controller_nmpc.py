"""NMPC (CasADi/IPOPT, multiple shooting, RK4) on the linear double as its model.

Fast checks only; the closed loop on the real plant is in test_controller_closed_loop.py.
"""
from __future__ import annotations

import dataclasses
import math

import casadi as ca
import numpy as np
import pytest

from controller.base import STEER_LIMIT_RAD, SolverStatus
from controller.nmpc import Nmpc, _augmented_dynamics, rk4_step
from controller.tuning import load_tuning
from test_controller_doubles import TS, bicycle_dynamics_casadi
from test_controller_qp import LinearPlant, run, straight


def build(**overrides) -> Nmpc:
    tuning = load_tuning()
    return Nmpc(bicycle_dynamics_casadi, dataclasses.replace(tuning.nmpc, **overrides), tuning.longitudinal)


def test_straight_path_converges_and_reports_ipopt_statistics() -> None:
    errors, commands, debugs = run(build(), straight(), LinearPlant((0.0, 1.0, 0.0)), 160)
    times = np.array([d.solve_time_s for d in debugs]) * 1e3
    iterations = [d.iterations for d in debugs]
    print(f"e_Y start {errors[0]:.3f} m, after 4 s {errors[-1]:.2e} m; IPOPT wall time median "
          f"{np.median(times):.1f} ms, iterations {min(iterations)}..{max(iterations)}")
    assert all(d.status == SolverStatus.SOLVED and not d.fallback for d in debugs)
    assert abs(errors[-1]) < 5e-3
    assert np.all(times > 0) and min(iterations) >= 1


def test_predicted_trajectory_is_the_models_rk4_rollout() -> None:
    controller = build()
    plant = LinearPlant((0.0, 0.7, 0.05))
    controller.set_path(straight())
    sample = plant.sample()
    command, debug = controller.step(sample)
    plan = controller._plan_steer
    derivatives = _augmented_dynamics(bicycle_dynamics_casadi)
    state = np.concatenate((sample.state(), sample.pose()))
    worst = 0.0
    for i in range(controller.tuning.prediction_horizon):
        state = np.asarray(rk4_step(derivatives, state, plan[min(i, plan.size - 1)], command.drive_torque, TS)).ravel()
        predicted = np.concatenate((debug.predicted_state[i], debug.predicted_pose[i]))
        worst = max(worst, float(np.max(np.abs(state - predicted))))
    print(f"max |shooting trajectory - RK4 rollout of the plan| = {worst:.2e}")
    assert worst < 1e-6


def test_steering_limit_holds() -> None:
    errors, commands, debugs = run(build(p_steer_rate=1.0), straight(), LinearPlant((0.0, 6.0, 0.0)), 60)
    steer = np.array([c.steer_angle for c in commands])
    print(f"min steer {steer.min():.4f}, max {steer.max():.4f} rad")
    assert np.all(np.abs(steer) <= STEER_LIMIT_RAD) and steer.min() == pytest.approx(-STEER_LIMIT_RAD, abs=1e-4)


def test_iteration_limit_gives_flagged_fallback_within_limits() -> None:
    errors, commands, debugs = run(build(ipopt_max_iter=1), straight(), LinearPlant((0.0, 2.0, 0.0)), 4)
    print([(d.status.name, d.fallback, c.steer_angle) for c, d in zip(commands, debugs)])
    assert all(d.fallback and d.status == SolverStatus.MAX_ITERATIONS for d in debugs)
    assert all(abs(c.steer_angle) <= STEER_LIMIT_RAD and math.isfinite(c.drive_torque) for c in commands)


def test_non_finite_sample_is_not_run() -> None:
    controller = build()
    controller.set_path(straight())
    bad = dataclasses.replace(LinearPlant((0.0, 0.0, 0.0)).sample(), vy=math.inf)
    command, debug = controller.step(bad)
    assert debug.status == SolverStatus.NOT_RUN and debug.fallback and command.steer_angle == 0.0


def test_casadi_dynamics_double_matches_numpy_double() -> None:
    """Guards the double itself: its casadi form is the bicycle the QP tests use."""
    from test_controller_doubles import BicycleDouble

    a, b = BicycleDouble().continuous_matrices(10.0)
    state = np.array([10.0, 0.3, -0.1])
    derivative = np.asarray(bicycle_dynamics_casadi(ca.DM(state), 0.05, 0.0)).ravel()
    expected = a @ state[1:] + b[:, 0] * 0.05
    print(derivative, expected)
    assert np.allclose(derivative[1:], expected) and derivative[0] == 0.0

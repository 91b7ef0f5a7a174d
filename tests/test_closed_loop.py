"""studies.closed_loop: HIL timing, recording and failure handling (with doubles), and short
runs of the real controllers on the real plant."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from controller.base import STEER_LIMIT_RAD
from controller.registry import create_controller
from studies.closed_loop import ABORT_LATERAL_ERROR_M, run_closed_loop
from hil.errors import StudyError
from hil.scenario import SpeedProfile, load_scenario
from tests.test_closed_loop_doubles import (KinematicCommand, KinematicPlant, PurePursuit,
                                       ScriptedController)


def smoke():
    return load_scenario("dlc_smoke")


def run_double(scenario, controller, plant=None):
    plant = plant or KinematicPlant()
    return run_closed_loop(scenario, controller, plant=plant, command_type=KinematicCommand), plant


def test_plant_ticks_and_command_hold_follow_the_lockstep_contract() -> None:
    scenario = replace(smoke(), duration_s=1.0)
    controller = ScriptedController(lambda k: 0.001 * (k + 1))
    result, plant = run_double(scenario, controller)
    # 1 s = 200 ticks of 5 ms; 40 control steps at t = 0, 25, ... 975 ms.
    assert len(plant.steps) == 200 and all(dt == 0.005 for dt, _, _ in plant.steps)
    np.testing.assert_allclose(result.trace.time_s, 0.025 * np.arange(40))
    applied = np.array([steer for _, steer, _ in plant.steps])
    # Command k is applied from its own tick on, for the 5 ticks of the control period.
    np.testing.assert_allclose(applied, np.repeat(0.001 * np.arange(1, 41), 5))


def test_controller_sees_the_newest_10ms_sample_and_the_profile() -> None:
    # Straight at 1 m/s along X from 0: the sample's x is the time it was published.
    scenario = replace(smoke(), duration_s=0.2, speed_profile=SpeedProfile((0.0, 0.2), (1.0, 3.0)))
    scenario = replace(scenario, start=replace(scenario.start, x_m=0.0, y_m=0.0, yaw_rad=0.0,
                                               speed_mps=1.0))
    controller = ScriptedController(lambda k: 0.0)
    result, _ = run_double(scenario, controller)
    seen_x = np.array([s.x for s in controller.samples])
    control_t = 0.025 * np.arange(8)
    published_t = np.floor(control_t / 0.010 + 1e-9) * 0.010      # newest 10 ms sample
    print("sample ages (ms):", np.round((control_t - seen_x) * 1000, 3))
    np.testing.assert_allclose(seen_x, published_t, atol=1e-12)
    np.testing.assert_allclose(result.trace.x, control_t, atol=1e-12)   # trace: true state
    np.testing.assert_allclose([s.target_speed for s in controller.samples],
                               1.0 + 10.0 * control_t)


def test_pure_pursuit_double_tracks_the_smoke_lane_change() -> None:
    result, _ = run_double(smoke(), PurePursuit())
    trace = result.trace
    print(f"pure pursuit: max |e_Y| {result.tracking.lateral.max_abs:.3f} m, "
          f"RMSE {result.tracking.lateral.rmse:.3f} m, Y {trace.y.min():.2f} .. {trace.y.max():.2f}")
    assert result.completed and result.failure is None
    assert len(trace) == 160
    assert trace.y.max() > 3.0                        # it did drive the lane change
    assert result.tracking.lateral.max_abs < 0.5
    assert result.steer_limit_held
    assert result.tracking.lateral.rmse == pytest.approx(
        math.sqrt(np.mean(trace.lateral_error**2)))
    assert set(trace.columns()) >= {"time_s", "x", "y", "yaw", "vx", "steer_cmd", "torque_cmd",
                                    "lateral_error", "heading_error", "solver_status",
                                    "solve_time_s", "step_time_s", "fallback"}
    assert all(v.shape == (160,) for v in trace.columns().values())
    assert np.all(trace.step_time_s > 0) and result.compute_time.steps == 159


def test_steering_off_the_road_aborts_with_the_reason() -> None:
    result, _ = run_double(smoke(), ScriptedController(lambda k: 0.3))
    print(result.failure)
    assert not result.completed
    assert f"> {ABORT_LATERAL_ERROR_M} m" in result.failure
    assert abs(result.trace.lateral_error[-1]) > ABORT_LATERAL_ERROR_M
    assert result.trace.time_s[-1] < smoke().duration_s


def test_out_of_limit_command_is_reported() -> None:
    result, _ = run_double(replace(smoke(), duration_s=0.5),
                           ScriptedController(lambda k: 0.35 if k == 3 else 0.0))
    assert result.completed and not result.steer_limit_held
    assert result.fallback_steps == 10            # the double flags every second step


@pytest.mark.parametrize(
    "controller, message",
    [
        (ScriptedController(lambda k: float("nan") if k == 5 else 0.0), "non-finite command"),
        (ScriptedController(lambda k: 0.0, raise_at=4), "controller.step raised at t = 0.100"),
    ],
)
def test_controller_failures_end_the_run_without_raising(controller, message: str) -> None:
    result, _ = run_double(smoke(), controller)
    assert not result.completed and message in result.failure


def test_result_saves_its_trace(tmp_path) -> None:
    result, _ = run_double(replace(smoke(), duration_s=0.5), PurePursuit())
    result.save_npz(tmp_path / "run.npz")
    with np.load(tmp_path / "run.npz") as data:
        np.testing.assert_array_equal(data["lateral_error"], result.trace.lateral_error)
        assert str(data["controller"]) == "pure-pursuit" and bool(data["completed"])


# --- the real plant and controllers -----------------------------------------------------


@pytest.mark.parametrize("name", ["lmpc", "eso-dkmpc"])
def test_real_controller_drives_the_smoke_scenario(name: str) -> None:
    controller = create_controller(name)
    result = run_closed_loop(smoke(), controller)
    trace = result.trace
    print(f"{name}: completed {result.completed} ({result.failure}), max |e_Y| "
          f"{result.tracking.lateral.max_abs:.3f} m, RMSE {result.tracking.lateral.rmse:.3f} m, "
          f"max |heading| {result.tracking.heading.max_abs:.3f} rad, max |steer| "
          f"{np.abs(trace.steer_cmd).max():.3f} rad, fallbacks {result.fallback_steps}, "
          f"median step {result.compute_time.median_s * 1e3:.1f} ms")
    assert result.completed, result.failure
    assert len(trace) == 160
    assert np.all(np.abs(trace.steer_cmd) <= STEER_LIMIT_RAD)
    assert np.all(np.abs(trace.steer_angle) <= STEER_LIMIT_RAD + 1e-9)
    assert result.tracking.lateral.max_abs < 0.5
    assert trace.y.max() > 3.0
    assert result.fallback_steps == 0


def test_plant_period_option_gives_fresh_samples_and_is_validated() -> None:
    scenario = replace(smoke(), duration_s=0.2)
    scenario = replace(scenario, start=replace(scenario.start, x_m=0.0, y_m=0.0, yaw_rad=0.0,
                                               speed_mps=1.0))
    controller = ScriptedController(lambda k: 0.0)
    run_closed_loop(scenario, controller, plant=KinematicPlant(), command_type=KinematicCommand,
                    plant_period_ms=5)
    np.testing.assert_allclose([s.x for s in controller.samples], 0.025 * np.arange(8),
                               atol=1e-12)
    with pytest.raises(StudyError, match="plant_period_ms = 7"):
        run_closed_loop(scenario, controller, plant=KinematicPlant(),
                        command_type=KinematicCommand, plant_period_ms=7)

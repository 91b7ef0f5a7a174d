"""Unit tests of the ECU's pieces: dead reckoning (eq. 20), guard, safe stop, lockstep
clock, real-time schedule, timing ring buffer, RX sample assembly."""
from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from can_defs.frames import FrameId, VehDyn, VehPoseXY, VehPoseYaw

from controller.base import VehicleSample
from controller.dead_reckoning import predict_pose, predict_sample
from firmware_sim.clock import HANDSHAKE_TICK, LockstepClock, RealtimeSchedule, TickKind
from firmware_sim.config import EcuConfig
from firmware_sim.errors import ConfigError
from firmware_sim.guard import GuardLimits, guard_command
from firmware_sim.safe_stop import safe_stop_command
from firmware_sim.timing import TIMING_FIELDS, TimingRecorder
from models.plant_sample import PlantSampleAssembler


# ------------------------------------------------------------------ dead reckoning
def test_dead_reckoning_straight_line_and_circle():
    pose = predict_pose(np.array([1.0, 2.0, 0.0]), np.array([10.0, 0.0, 0.0]), 0.1)
    print("straight 0.1 s at 10 m/s:", pose)
    assert pose == pytest.approx([2.0, 2.0, 0.0], abs=1e-12)
    # constant yaw rate: Euler steps of eq. 20 (Ts = 0.025) vs the exact arc
    speed, yaw_rate, elapsed = 10.0, 0.5, 0.1
    pose = predict_pose(np.zeros(3), np.array([speed, 0.0, yaw_rate]), elapsed)
    radius = speed / yaw_rate
    exact = np.array([radius * math.sin(yaw_rate * elapsed),
                      radius * (1 - math.cos(yaw_rate * elapsed)), yaw_rate * elapsed])
    error = np.abs(pose - exact).max()
    print(f"arc 0.1 s: eq. 20 {pose}, exact {exact}, max |error| {error:.2e}")
    assert pose[2] == pytest.approx(0.05, abs=1e-12)
    # forward Euler's error over the arc: about vx * r * T * Ts / 2 = 6.25 mm
    assert error < 1.05 * speed * yaw_rate * elapsed * 0.025 / 2


def test_dead_reckoning_matches_hand_computed_eq_20_steps():
    vx, vy, r = 8.0, 0.5, 0.2
    x = y = yaw = 0.0
    for dt in (0.025, 0.025, 0.01):             # 60 ms: two full steps and a short one
        x, y, yaw = (x + dt * (vx * math.cos(yaw) - vy * math.sin(yaw)),
                     y + dt * (vx * math.sin(yaw) + vy * math.cos(yaw)), yaw + dt * r)
    pose = predict_pose(np.zeros(3), np.array([vx, vy, r]), 0.06)
    print("60 ms:", pose, "hand:", (x, y, yaw), "max diff", np.abs(pose - [x, y, yaw]).max())
    assert pose == pytest.approx([x, y, yaw], abs=1e-12)


def test_dead_reckoning_wraps_yaw_and_keeps_the_rest_of_the_sample():
    sample = VehicleSample(vx=5.0, vy=0.1, yaw_rate=2.0, x=0.0, y=0.0, yaw=3.1,
                           steer_angle=0.05, drive_torque=120.0, target_speed=6.0)
    predicted = predict_sample(sample, 0.05)
    assert -math.pi <= predicted.yaw < math.pi and predicted.yaw < 0  # 3.2 wrapped
    assert (predicted.vx, predicted.vy, predicted.yaw_rate, predicted.steer_angle,
            predicted.drive_torque, predicted.target_speed) == (5.0, 0.1, 2.0, 0.05, 120.0, 6.0)
    assert predict_sample(sample, 0.0) == sample


@pytest.mark.parametrize("elapsed", [-0.01, math.nan, math.inf])
def test_dead_reckoning_refuses_bad_elapsed_time(elapsed):
    with pytest.raises(ValueError, match="elapsed_s"):
        predict_pose(np.zeros(3), np.ones(3), elapsed)


def test_dead_reckoning_refuses_non_finite_state():
    with pytest.raises(ValueError, match="non-finite"):
        predict_pose(np.zeros(3), np.array([math.nan, 0, 0]), 0.1)


# ------------------------------------------------------------------ guard
LIMITS = GuardLimits(steer_limit_rad=0.3, drive_torque_limit_nm=3000.0)


@pytest.mark.parametrize("steer, torque, reason", [
    (math.nan, 0.0, "not finite"), (0.1, math.inf, "not finite"), (0.31, 0.0, "steer_angle"),
    (-0.3001, 0.0, "steer_angle"), (0.0, 3000.1, "drive_torque"), (0.0, -1e9, "drive_torque")])
def test_guard_refuses_non_finite_and_out_of_limit(steer, torque, reason):
    result = guard_command(steer, torque, LIMITS, previous_valid_steer=0.12)
    print(result)
    assert result.refused is not None and reason in result.refused
    assert (result.steer_angle, result.drive_torque) == (0.12, 0.0)


def test_guard_passes_limits_inclusive_and_clamps_a_bad_previous_steer():
    assert guard_command(0.3, -3000.0, LIMITS, 0.0).refused is None
    assert guard_command(-0.3, 3000.0, LIMITS, 0.0).refused is None
    assert guard_command(math.nan, 0.0, LIMITS, 0.9).steer_angle == 0.3
    assert guard_command(math.nan, 0.0, LIMITS, math.nan).steer_angle == 0.0


def test_guard_limits_never_exceed_the_dbc_range():
    wide = GuardLimits(steer_limit_rad=10.0, drive_torque_limit_nm=1e6)
    assert wide.torque_range() == (-3276.8, 3276.7)
    assert guard_command(0.0, 3276.75, wide, 0.0).refused is not None


# ------------------------------------------------------------------ safe stop
def test_safe_stop_ramps_steer_to_zero_at_bounded_rate_and_brakes_until_standstill():
    steer, history = 0.2, []
    for _ in range(50):
        command = safe_stop_command(steer, standstill=False, period_s=0.025,
                                    steer_rate_rad_s=0.2, brake_torque_nm=1500.0)
        history.append(command.steer_angle)
        assert command.drive_torque == -1500.0
        steer = command.steer_angle
    steps = np.abs(np.diff([0.2] + history))
    print("steer after 10 cycles:", history[9], "largest step:", steps.max())
    assert steps.max() <= 0.005 + 1e-12 and history[-1] == 0.0
    at_rest = safe_stop_command(-0.001, True, 0.025, 0.2, 1500.0)
    assert (at_rest.steer_angle, at_rest.drive_torque) == (0.0, 0.0)


# ------------------------------------------------------------------ clocks
def test_lockstep_clock_due_instants():
    clock = LockstepClock(task_period_ms=25, max_catch_up_tasks=40)
    assert clock.advance(0).kind is TickKind.NOT_SYNCHRONISED
    assert clock.advance(HANDSHAKE_TICK).kind is TickKind.HANDSHAKE
    due = [clock.advance(t).due_ms for t in range(0, 55, 5)]
    print("due instants per tick:", due)
    assert [d for d in due if d] == [(0,), (25,), (50,)]
    assert clock.advance(50).kind is TickKind.REPEATED
    assert clock.advance(45).kind is TickKind.BACKWARDS
    near = clock.advance(150)  # 100 ms ahead: not a jump, every due instant runs
    assert near.kind is TickKind.NEW and near.due_ms == (75, 100, 125, 150)
    # issue 17 defect 9: a TICK far ahead ran 40 catch-up tasks on one sample. Rev. 2: a
    # jump of virtual time is adopted, only the task due at the TICK itself runs.
    jump = clock.advance(2000)
    assert jump.kind is TickKind.JUMP
    assert jump.due_ms == (2000,) and jump.skipped == 73  # 74 instants in (150, 2000]
    assert clock.advance(2005).kind is TickKind.NEW  # and time goes on from there
    clock.advance(HANDSHAKE_TICK)
    assert clock.advance(95).kind is TickKind.NEW  # after the handshake the last TICK is -5
    clock.advance(HANDSHAKE_TICK)
    assert clock.advance(105).kind is TickKind.JUMP


def test_realtime_schedule_keeps_absolute_deadlines_and_skips_missed_periods():
    period = 25_000_000
    schedule = RealtimeSchedule(period)
    schedule.start(1_000)
    releases = []
    for now in (1_000, 27_000_000, 51_500_000):              # late by 0, ~2 ms, 0.5 ms
        assert schedule.due(now)
        releases.append(schedule.release(now))
    print("(ideal release, skipped):", releases)
    assert [ideal for ideal, _ in releases] == [1_000, 25_001_000, 50_001_000]  # no drift
    assert not schedule.due(60_000_000)
    ideal, skipped = schedule.release(140_000_000)            # 65 ms late: 2 periods missed
    assert (ideal, skipped) == (75_001_000, 2) and schedule.next_release_ns == 150_001_000


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="drive_torque_limit_nm"):
        EcuConfig(drive_torque_limit_nm=4000.0)
    with pytest.raises(ConfigError, match="control_period_ms"):
        EcuConfig(control_period_ms=0)
    with pytest.raises(ConfigError, match="steer_limit_rad"):
        EcuConfig(steer_limit_rad=math.nan)


# ------------------------------------------------------------------ timing record
def test_timing_ring_buffer_wraps_and_summarises():
    recorder = TimingRecorder(capacity=100)
    buffer_id = id(recorder._rows)
    for cycle in range(250):
        recorder.record(cycle * 1e-6, 1e-3, 5e-4, math.nan, 2e-3, cycle)
    rows = recorder.rows()
    assert rows.shape == (100, len(TIMING_FIELDS)) and id(recorder._rows) == buffer_id
    assert rows[0, 5] == 150 and rows[-1, 5] == 249           # oldest first, last 100 kept
    summary = recorder.summary()
    print("release_jitter summary:", summary["release_jitter"])
    assert summary["release_jitter"]["max"] == pytest.approx(249e-6)
    assert summary["release_jitter"]["p50"] == pytest.approx(199.5e-6)
    assert summary["input_age"]["n"] == 0 and math.isnan(summary["input_age"]["p99"])


def test_timing_record_allocates_nothing_per_cycle():
    recorder = TimingRecorder(capacity=1000)
    recorder.record(0.0, 0.0, 0.0, 0.0, 0.0, 0)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for _ in range(500):
        recorder.record(1e-5, 1e-3, 5e-4, 2e-3, 2e-3, 0)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(stat.size_diff for stat in after.compare_to(before, "filename")
                if "timing.py" in str(stat.traceback))
    print("bytes allocated in timing.py over 500 records:", grown)
    assert grown < 1024


# ------------------------------------------------------------------ sample assembly
def test_sample_assembler_needs_all_three_frames_with_one_counter():
    assembler = PlantSampleAssembler()
    dyn, xy, yaw = VehDyn(10.0, 0.1, 0.01), VehPoseXY(1.0, 2.0), VehPoseYaw(0.1, 0.02, 50.0)
    assert assembler.add(FrameId.VEH_DYN, dyn, 3) == (None, False)
    assert assembler.add(FrameId.VEH_POSE_XY, xy, 3) == (None, False)
    measurement, torn = assembler.add(FrameId.VEH_POSE_YAW, yaw, 3)
    assert measurement is not None and not torn and measurement.x == 1.0 and measurement.counter == 3
    assert assembler.add(FrameId.VEH_POSE_YAW, yaw, 3) == (None, False)  # late duplicate unused
    # counter 4 incomplete, then counter 5 starts: 4 was torn and is dropped
    assert assembler.add(FrameId.VEH_DYN, dyn, 4) == (None, False)
    assert assembler.add(FrameId.VEH_POSE_XY, xy, 5) == (None, True)
    # a set mixing counters never completes
    assert assembler.add(FrameId.VEH_POSE_YAW, yaw, 6) == (None, True)
    assert assembler.add(FrameId.VEH_DYN, dyn, 6)[0] is None

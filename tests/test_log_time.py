"""Lockstep logs are stamped with virtual time (issue 19): every frame carries the
wall-clock start plus the virtual time of its tick, so third-party tools see the drive at
its true speed; the sidecar keeps the wall clock; the replay still matches bit for bit.
Real-time logs keep the bus's wall clock."""
from __future__ import annotations

import dataclasses
import time

import can
import pytest

from can_defs.codec import encode
from can_defs.frames import HANDSHAKE_TICK, FrameId, HilSync
from hil.logio import TickStamper, frame_times, read_log, read_sidecar
from hil.replay import run_replay
from hil.scenario import load_scenario
from hil.session import default_options, run_hil

CONTROLLER = "lmpc"
DURATION_S = 1.0
TICK_S = 0.005


@pytest.fixture(scope="module")
def lockstep_log(tmp_path_factory):
    scenario = dataclasses.replace(load_scenario("dlc_smoke"), duration_s=DURATION_S)
    log = tmp_path_factory.mktemp("lockstep") / "run.log"
    before = time.time()
    result = run_hil(scenario, default_options(CONTROLLER, log_path=log))
    return log, result, before, time.time()


def test_a_lockstep_log_spans_the_scenario_duration(lockstep_log) -> None:
    log, result, before, after = lockstep_log
    frames = list(can.LogReader(log))  # python-can's own reader, as a third-party tool
    span = frames[-1].timestamp - frames[0].timestamp
    print(f"{len(frames)} frames, log span {span:.4f} s for a {DURATION_S} s scenario; "
          f"the run took {result.wall_time_s:.2f} s of wall clock")
    assert abs(span - DURATION_S) <= TICK_S + 1e-5  # float resolution of Unix time
    # Non-decreasing timestamps: players (can.MessageSync, canplayer) play them in order.
    assert all(b.timestamp >= a.timestamp - 1e-5 for a, b in zip(frames, frames[1:]))
    # The timestamp is the start plus the virtual time the replay derives from HIL_SYNC.
    times, base = frame_times(read_log(log).messages)
    assert "virtual time" in base
    assert max(abs(f.timestamp - frames[0].timestamp - t) for f, t in zip(frames, times)) < 1e-5


def test_the_sidecar_keeps_the_wall_clock(lockstep_log) -> None:
    log, result, before, after = lockstep_log
    metadata = read_sidecar(log)
    first = next(iter(can.LogReader(log)))
    print(f"wall_start {metadata.wall_start:.3f}, wall_end {metadata.wall_end:.3f}, "
          f"first frame {first.timestamp:.3f}")
    assert before - 1 <= metadata.wall_start <= metadata.wall_end <= after + 1
    assert first.timestamp == pytest.approx(metadata.wall_start, abs=1e-5)  # candump: 1 us


def test_the_virtual_time_log_still_replays_bit_for_bit(lockstep_log) -> None:
    log, *_ = lockstep_log
    metadata = read_sidecar(log)
    report = run_replay(read_log(log), metadata.controller,
                        {k: v for k, v in metadata.paths.items()})
    print(report.text())
    assert report.comparison.mode == "exact"
    assert report.match and report.comparison.paired == report.comparison.expected > 40


def test_a_realtime_log_keeps_the_wall_clock(tmp_path) -> None:
    scenario = dataclasses.replace(load_scenario("dlc_smoke"), duration_s=0.3)
    log = tmp_path / "rt.log"  # candump keeps absolute timestamps (ASC: relative)
    before = time.time()
    run_hil(scenario, default_options(CONTROLLER, log_path=log, lockstep=False))
    frames = list(can.LogReader(log))
    metadata = read_sidecar(log)
    print(f"real-time log: first frame {frames[0].timestamp:.3f}, run started {before:.3f}")
    assert metadata.mode == "realtime"
    assert abs(frames[0].timestamp - metadata.wall_start) < 1e-3
    assert before - 1 <= frames[0].timestamp <= time.time()


def _sync(tick: int) -> can.Message:
    return can.Message(arbitration_id=int(FrameId.HIL_SYNC), data=encode(HilSync(tick)),
                       is_extended_id=False)


def _ack(tick: int) -> can.Message:
    return can.Message(arbitration_id=int(FrameId.HIL_SYNC_ACK),
                       data=tick.to_bytes(4, "little") + bytes(4), is_extended_id=False)


def test_the_stamper_settles_frames_as_the_protocol_says() -> None:
    """Handshake frames get the first tick, inputs the tick of the HIL_SYNC after them,
    the ECU's answers the tick before them; frames come out in arrival order."""
    plant = can.Message(arbitration_id=int(FrameId.VEH_DYN), data=bytes(8), is_extended_id=False)
    command = can.Message(arbitration_id=int(FrameId.STEER_TORQUE_CMD), data=bytes(8),
                          is_extended_id=False)
    stream = [_sync(HANDSHAKE_TICK), _ack(HANDSHAKE_TICK), plant, _sync(0), _ack(0), command,
              plant, _sync(5), _ack(5), plant]
    stamper = TickStamper()
    settled = []
    for message in stream:
        settled.extend(stamper.push(message))
    assert len(settled) == 9  # the last plant frame waits for a HIL_SYNC that never comes
    settled.extend(stamper.flush())
    assert [m for m, _ in settled] == stream
    assert [t for _, t in settled] == [0, 0, 0, 0, 0, 0, 5, 5, 5, 5]

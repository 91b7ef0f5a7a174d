"""hil.replay: feeding logs into the ECU, the lockstep protocol, and the comparison.

Fast tests use synthetic logs made with can_defs and the ECU with a scripted controller
(hil.ecu_harness); the recorded-log regression tests are in test_replay_logs.py.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import can
import pytest

from can_defs.codec import FrameSender, encode
from can_defs.frames import (HANDSHAKE_TICK, CtrlDiag, CtrlMode, FrameId, HilSync, HilSyncAck,
                             PlannerReq, QpStatus, SteerTorqueCmd, VehDyn, VehPoseXY, VehPoseYaw)
from hil.ecu_harness import ScriptedController
from hil import replay_feed
from hil.logio import LogContents
from hil.replay import (OutputFrame, ReplayError, compare_outputs, exact_masks, read_reference,
                        replay_log, run_replay, write_reference)

PATHS = {1: Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"}


def _message(frame_id: int, data: bytes, timestamp: float) -> can.Message:
    return can.Message(timestamp=timestamp, arbitration_id=int(frame_id), data=data,
                       is_extended_id=False)


def synthetic_lockstep_log(duration_ms: int = 300, handshake: bool = True,
                           lateral_offset: float = 0.05) -> LogContents:
    """Master frames of a lockstep run (no ECU frames): plant every 10 ms at 10 m/s along
    the X axis ``lateral_offset`` m left of it, planner engaged every 25 ms."""
    plant, planner = FrameSender(), FrameSender()
    messages = []
    wall = 1000.0
    if handshake:
        messages.append(_message(FrameId.HIL_SYNC, encode(HilSync(HANDSHAKE_TICK)), wall))
    for tick in range(0, duration_ms, 5):
        wall += 0.001
        if tick % 10 == 0:
            x = 10.0 + 10.0 * tick / 1000.0
            for frame in (VehDyn(10.0, 0.0, 0.0), VehPoseXY(x, lateral_offset), VehPoseYaw(0.0, 0.0, 0.0)):
                messages.append(_message(frame.FRAME_ID, plant.encode(frame), wall))
        if tick % 25 == 0:
            messages.append(_message(FrameId.PLANNER_REQ,
                                     planner.encode(PlannerReq(True, 10.0, 1)), wall))
        messages.append(_message(FrameId.HIL_SYNC, encode(HilSync(tick)), wall))
    contents = LogContents(path=Path("synthetic.log"), messages=messages)
    for message in messages:
        contents.frames_by_id[message.arbitration_id] += 1
    return contents


def scripted(name: str) -> ScriptedController:
    return ScriptedController()


def _cmd(time_s: float, steer: float, counter: int = 0, mode: CtrlMode = CtrlMode.ACTIVE) -> OutputFrame:
    return OutputFrame(time_s, FrameId.STEER_TORQUE_CMD,
                       encode(SteerTorqueCmd(mode, True, steer, 100.0), counter))


def _diag(time_s: float, solve_us: int, iterations: int = 7, counter: int = 0) -> OutputFrame:
    return OutputFrame(time_s, FrameId.CTRL_DIAG,
                       encode(CtrlDiag(QpStatus.SOLVED, solve_us, solve_us + 50, iterations, 0, 0),
                              counter))


# --- comparison -----------------------------------------------------------------------


def test_exact_masks_leave_out_ctrl_diag_timing_and_crc() -> None:
    masks = exact_masks()
    print({hex(k): v.hex() for k, v in masks.items()})
    assert masks[FrameId.STEER_TORQUE_CMD] == bytes([0xFF] * 8)
    # CRC byte 0, SOLVE_TIME_US bytes 2-3, CYCLE_TIME_US bytes 4-5, OVERRUNS bits 56..59.
    assert masks[FrameId.CTRL_DIAG] == bytes([0x00, 0xFF, 0, 0, 0, 0, 0xFF, 0xF0])


def test_identical_frames_match_even_with_other_timing_fields() -> None:
    expected = [_cmd(0.0, 0.01), _diag(0.0, 300), _cmd(0.025, 0.02, 1), _diag(0.025, 310, counter=1)]
    replayed = [_cmd(0.0, 0.01), _diag(0.0, 999), _cmd(0.025, 0.02, 1), _diag(0.025, 5, counter=1)]
    result = compare_outputs(expected, replayed)
    print(result)
    assert result.match and result.paired == 4 and result.first_divergence is None


def test_one_lsb_of_steering_is_the_first_divergence() -> None:
    expected = [_cmd(0.0, 0.01), _cmd(0.025, 0.02, 1), _cmd(0.05, 0.03, 2)]
    replayed = [_cmd(0.0, 0.01), _cmd(0.025, 0.0201, 1), _cmd(0.05, 0.0305, 2)]
    result = compare_outputs(expected, replayed)
    diff = result.signals["STEER_TORQUE_CMD.steer_angle_cmd"]
    print(result.first_divergence.text(), diff)
    assert not result.match and result.mismatched_frames == 2
    assert result.first_divergence.time_s == 0.025
    assert result.first_divergence.signal == "steer_angle_cmd"
    assert diff.max_abs_diff == pytest.approx(5e-4) and diff.mismatches == 2
    # The same frames are within the default steering tolerance (2e-3 rad) per signal.
    assert compare_outputs(expected, replayed, mode="tolerance").match
    tight = compare_outputs(expected, replayed, mode="tolerance", tolerances={"steer_angle_cmd": 2e-4})
    assert tight.mismatched_frames == 1 and tight.first_divergence.time_s == 0.05


def test_a_counter_difference_alone_breaks_the_exact_comparison() -> None:
    result = compare_outputs([_cmd(0.0, 0.01, counter=3)], [_cmd(0.0, 0.01, counter=4)])
    print(result.first_divergence.text())
    assert result.first_divergence.signal == "counter"
    assert compare_outputs([_cmd(0.0, 0.01, counter=3)], [_cmd(0.0, 0.01, counter=4)],
                           mode="tolerance").match


def test_missing_and_extra_frames_are_reported_with_their_time() -> None:
    expected = [_cmd(0.0, 0.0), _cmd(0.025, 0.0), _cmd(0.05, 0.0)]
    replayed = [_cmd(0.0, 0.0), _cmd(0.05, 0.0), _cmd(0.075, 0.0)]
    result = compare_outputs(expected, replayed)
    print(result.first_divergence.text())
    assert (result.paired, result.missing, result.extra) == (2, 1, 1)
    assert result.first_divergence.time_s == 0.025 and result.first_divergence.signal == "(frame)"
    # Pairing within a window tolerates jitter of time-stamped logs.
    jittered = [_cmd(0.003, 0.0), _cmd(0.027, 0.0), _cmd(0.049, 0.0)]
    assert compare_outputs(expected, jittered, window_s=0.0125).match


def test_extra_frames_after_a_cut_log_can_be_ignored() -> None:
    result = compare_outputs([_cmd(0.0, 0.0)], [_cmd(0.0, 0.0), _cmd(0.025, 0.0)],
                             ignore_extra_after_s=0.0)
    assert result.match and result.extra_ignored == 1


def test_bad_comparison_mode_is_refused() -> None:
    with pytest.raises(ReplayError, match="'exact' or 'tolerance'"):
        compare_outputs([], [], mode="fuzzy")


def test_reference_file_round_trip(tmp_path: Path) -> None:
    frames = [_cmd(0.0, 0.01), _diag(0.0, 300), _cmd(0.025, -0.02, 1)]
    path = write_reference(tmp_path / "x.ref.log", frames)
    loaded, _ = read_reference(path)
    assert [f.time_s for f in loaded] == pytest.approx([0.0, 0.0, 0.025])
    assert loaded[0].data == frames[0].data and loaded[2].data == frames[2].data
    # CTRL_DIAG is stored with its measured timing zeroed and a valid CRC, so regenerated
    # references change only where behaviour changed; it still compares equal.
    from can_defs.codec import decode
    diag = decode(FrameId.CTRL_DIAG, loaded[1].data)
    print(diag)
    assert diag.crc_ok and (diag.frame.solve_time_us, diag.frame.cycle_time_us) == (0, 0)
    assert diag.frame.qp_iter == 7
    assert compare_outputs(frames, loaded).match


# --- the lockstep protocol -------------------------------------------------------------


class ProtocolCheckingEcu:
    """ECU double on the replay's bus: answers HIL_SYNC after a delay with a command, then
    the ACK; records whether any frame arrived while an ACK was pending."""

    def __init__(self, bus: can.BusABC, silent_tick: int | None = None) -> None:
        self.bus = bus
        self.silent_tick = silent_tick
        self.received: list[tuple[int, bytes]] = []
        self.frames_while_pending = 0
        self.load_error = None

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            message = self.bus.recv(0.02)
            if message is None:
                continue
            self.received.append((message.arbitration_id, bytes(message.data)))
            if message.arbitration_id != FrameId.HIL_SYNC:
                continue
            tick = int.from_bytes(message.data[:4], "little")
            if tick == self.silent_tick:
                continue
            time.sleep(0.003)  # a replay that does not wait sends its next frames now
            while self.bus.recv(0.0) is not None:
                self.frames_while_pending += 1
            if tick != HANDSHAKE_TICK and tick % 25 == 0:
                self.bus.send(can.Message(arbitration_id=FrameId.STEER_TORQUE_CMD,
                                          data=encode(SteerTorqueCmd(CtrlMode.STANDBY, False, 0.0, 0.0)),
                                          is_extended_id=False))
            self.bus.send(can.Message(arbitration_id=FrameId.HIL_SYNC_ACK,
                                      data=encode(HilSyncAck(tick)), is_extended_id=False))

    def close(self) -> None:
        pass


def _patch_ecu(monkeypatch: pytest.MonkeyPatch, **kwargs: object) -> list[ProtocolCheckingEcu]:
    made: list[ProtocolCheckingEcu] = []

    def make(bus, *args, **_):
        made.append(ProtocolCheckingEcu(bus, **kwargs))
        return made[-1]

    monkeypatch.setattr(replay_feed, "_make_ecu", make)
    return made


def test_lockstep_replay_waits_for_every_ack(monkeypatch: pytest.MonkeyPatch) -> None:
    made = _patch_ecu(monkeypatch)
    log = synthetic_lockstep_log(duration_ms=100)
    run = replay_log(log, "any", PATHS)
    ecu = made[0]
    print(f"acks {run.acks}, frames sent while an ACK was pending: {ecu.frames_while_pending}")
    assert run.aborted is None
    assert run.acks == 1 + 20  # handshake + ticks 0..95
    assert ecu.frames_while_pending == 0
    assert [frame_id for frame_id, _ in ecu.received] == [m.arbitration_id for m in log.messages]
    # Outputs carry the virtual time of the TICK they answered.
    assert [o.time_s for o in run.outputs] == [0.0, 0.025, 0.05, 0.075]


def test_a_log_without_handshake_gets_one(monkeypatch: pytest.MonkeyPatch) -> None:
    made = _patch_ecu(monkeypatch)
    run = replay_log(synthetic_lockstep_log(duration_ms=50, handshake=False), "any", PATHS)
    print(run.notes)
    assert made[0].received[0] == (FrameId.HIL_SYNC, encode(HilSync(HANDSHAKE_TICK)))
    assert run.acks == 11 and "no lockstep handshake" in run.notes[0]


def test_a_missing_ack_stops_the_replay_with_a_partial_result(monkeypatch: pytest.MonkeyPatch) -> None:
    _patch_ecu(monkeypatch, silent_tick=50)
    run = replay_log(synthetic_lockstep_log(duration_ms=100), "any", PATHS, ack_timeout_s=0.2)
    print(run.aborted)
    assert "no HIL_SYNC_ACK for TICK=50 ms" in run.aborted
    assert [o.time_s for o in run.outputs] == [0.0, 0.025]


# --- the real ECU with a scripted controller ---------------------------------------------


def test_lockstep_replay_through_the_ecu_is_repeatable(tmp_path: Path) -> None:
    log = synthetic_lockstep_log(duration_ms=300)
    first = replay_log(log, "scripted", PATHS, controller_factory=scripted)
    second = replay_log(log, "scripted", PATHS, controller_factory=scripted)
    commands = [o for o in first.outputs if o.arbitration_id == FrameId.STEER_TORQUE_CMD]
    print(f"{len(first.outputs)} frames; commands at {[c.time_s for c in commands]}")
    # One command per control instant 0, 25, ..., 275 ms, plus the shutdown command.
    assert [c.time_s for c in commands] == pytest.approx([k * 0.025 for k in range(12)] + [0.295])
    assert compare_outputs(first.outputs, second.outputs).match
    # The ECU engages and steers gain * y = -0.01 * 0.05 m = -0.0005 rad.
    from can_defs.codec import decode
    modes = [decode(c.arbitration_id, c.data).frame for c in commands]
    assert modes[-2].ctrl_mode is CtrlMode.ACTIVE
    assert modes[-2].steer_angle_cmd == pytest.approx(-0.0005)


def test_run_replay_against_a_reference_and_its_report(tmp_path: Path) -> None:
    log = synthetic_lockstep_log(duration_ms=200)
    with pytest.raises(ReplayError, match="no STEER_TORQUE_CMD or CTRL_DIAG"):
        run_replay(log, "scripted", PATHS, controller_factory=scripted)
    written = run_replay(log, "scripted", PATHS, controller_factory=scripted, allow_no_expected=True)
    reference = write_reference(tmp_path / "s.ref.log", written.run.outputs)
    report = run_replay(log, "scripted", PATHS, reference=reference, controller_factory=scripted)
    print(report.text())
    assert report.match and report.comparison.mode == "exact"
    assert "result: MATCH" in report.text() and "first divergence: none" in report.text()
    # Another law (a different steering gain) diverges at the first active cycle.
    other = run_replay(log, "scripted", PATHS, reference=reference,
                       controller_factory=lambda name: ScriptedController(gain=-0.02))
    print(other.text())
    assert not other.match
    first = other.comparison.first_divergence
    assert (first.frame, first.signal) == ("STEER_TORQUE_CMD", "steer_angle_cmd")
    assert other.as_dict()["first_divergence"]["signal"] == "steer_angle_cmd"


def test_time_stamped_log_drives_the_ecu_on_the_log_clock() -> None:
    """Without HIL_SYNC the control task runs every 25 ms of log time, whatever the speed
    of the replay; the same inputs give the same commands as in lockstep."""
    lockstep = synthetic_lockstep_log(duration_ms=300)
    reference = replay_log(lockstep, "scripted", PATHS, controller_factory=scripted)
    # The same inputs with timestamps = virtual time, without HIL frames.
    from hil.logio import frame_times
    times, _ = frame_times(lockstep.messages)
    stamped = [_message(m.arbitration_id, bytes(m.data), 50.0 + t)
               for m, t in zip(lockstep.messages, times) if m.arbitration_id != FrameId.HIL_SYNC]
    log = LogContents(path=Path("stamped.log"), messages=stamped)
    run = replay_log(log, "scripted", PATHS, controller_factory=scripted, expected_end_s=0.295)
    print(f"{run.control_releases} releases; {run.notes[0]}")
    assert run.control_releases == 12
    assert compare_outputs(reference.outputs, run.outputs).match


def test_realtime_flag_paces_the_frames_by_the_log_timestamps(monkeypatch: pytest.MonkeyPatch) -> None:
    _patch_ecu(monkeypatch)
    log = synthetic_lockstep_log(duration_ms=100)
    # Spread the recorded wall-clock stamps to 10 ms per tick: 0.2 s of recording.
    for index, message in enumerate(log.messages):
        message.timestamp = 1000.0 + 0.2 * index / len(log.messages)
    span = log.messages[-1].timestamp - log.messages[0].timestamp
    started = time.monotonic()
    fast = replay_log(log, "any", PATHS)
    fast_s = time.monotonic() - started
    started = time.monotonic()
    paced = replay_log(log, "any", PATHS, realtime=True)
    paced_s = time.monotonic() - started
    print(f"recording spans {span:.3f} s; as fast as possible {fast_s:.3f} s, --realtime {paced_s:.3f} s")
    assert paced.acks == fast.acks == 21
    assert paced_s >= 0.9 * span

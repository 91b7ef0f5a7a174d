"""Receiver-side E2E checks (docs/can-contract.md "End-to-end protection")."""
from __future__ import annotations

import pytest
from hypothesis import given, settings, strategies as st

from can_defs import (CtrlDiag, CtrlMode, E2EMonitor, E2EReceiver, E2EStatus, FrameId,
                      FrameSender, HilSync, HilSyncAck, PlannerReq, QpStatus,
                      SteerTorqueCmd, UndefinedValueError, UnknownFrameError, VehDyn, VehPoseXY, VehPoseYaw,
                      decode, encode)

E2E_SAMPLES = [
    VehDyn(13.9, -0.21, 0.05),
    VehPoseXY(57.3, -2.4),
    VehPoseYaw(0.7, 0.02, 850.0),
    PlannerReq(True, 9.72, 1),
    SteerTorqueCmd(CtrlMode.ACTIVE, True, -0.11, 120.0),
    CtrlDiag(QpStatus.SOLVED, 850, 1900, 12, 0, 2),
]


def _frame_with_counter(frame, counter: int) -> bytes:
    return encode(frame, counter)


def test_every_single_bit_flip_is_a_crc_error():
    for frame in E2E_SAMPLES:
        payload = _frame_with_counter(frame, 5)
        detected = 0
        for bit in range(64):
            corrupted = bytearray(payload)
            corrupted[bit // 8] ^= 1 << (bit % 8)
            result = E2EReceiver(frame.FRAME_ID).check(bytes(corrupted))
            assert result.status is E2EStatus.CRC_ERROR and not result.accepted, bit
            try:
                assert not decode(frame.FRAME_ID, bytes(corrupted)).crc_ok, bit
            except UndefinedValueError:
                pass  # a flip into CTRL_MODE 6/7 or an undefined QP_STATUS: refused as well
            detected += 1
        print(f"{type(frame).__name__}: {detected}/64 single-bit flips detected")
        assert detected == 64


def test_frame_from_another_id_is_a_crc_error():
    """The ID is inside the CRC: a VEH_DYN payload received as VEH_POSE_XY is refused."""
    payload = encode(VehDyn(1.0, 0.0, 0.0), 1)
    result = E2EReceiver(FrameId.VEH_POSE_XY).check(payload)
    print(f"VEH_DYN payload on 0x101: {result}")
    assert result.status is E2EStatus.CRC_ERROR


def test_counter_wrap_15_to_0_is_ok():
    receiver = E2EReceiver(FrameId.VEH_DYN)
    sender = FrameSender()
    statuses = [receiver.check(sender.encode(VehDyn(0.0, 0.0, 0.0))).status for _ in range(40)]
    print(f"40 consecutive frames (2 wraps): {set(s.name for s in statuses)}, "
          f"stats {receiver.stats.counts[E2EStatus.OK]} OK, lost {receiver.stats.lost}")
    assert statuses == [E2EStatus.OK] * 40
    assert receiver.stats.lost == 0


JUMPS = [  # counter increment -> (status, lost, accepted)
    (1, E2EStatus.OK, 0, True),
    (2, E2EStatus.LOST, 1, True),
    (3, E2EStatus.LOST, 2, True),
    (0, E2EStatus.REPEATED, 0, False),
    (4, E2EStatus.SEQUENCE_ERROR, 3, False),
    (15, E2EStatus.SEQUENCE_ERROR, 14, False),
]


def test_counter_jumps_are_classified():
    frame = PlannerReq(True, 10.0, 0)
    for jump, status, lost, accepted in JUMPS:
        for start in (0, 14, 15):  # also across the wrap
            receiver = E2EReceiver(FrameId.PLANNER_REQ)
            assert receiver.check(encode(frame, start)).status is E2EStatus.OK  # synchronises
            result = receiver.check(encode(frame, (start + jump) % 16))
            assert (result.status, result.lost, result.accepted) == (status, lost, accepted), start
            assert receiver.stats.lost == lost
        print(f"jump {jump}: {result.status.name}, lost {result.lost}, accepted {result.accepted}")


def test_repeat_is_discarded_and_next_increment_still_ok():
    receiver = E2EReceiver(FrameId.VEH_DYN)
    frame = VehDyn(5.0, 0.0, 0.0)
    results = [receiver.check(encode(frame, c)) for c in (7, 7, 8)]
    print(f"counters 7, 7, 8: {[r.status.name for r in results]}")
    assert [r.status for r in results] == [E2EStatus.OK, E2EStatus.REPEATED, E2EStatus.OK]


def test_sequence_error_resynchronises_on_next_frame():
    receiver = E2EReceiver(FrameId.VEH_DYN)
    frame = VehDyn(5.0, 0.0, 0.0)
    results = [receiver.check(encode(frame, c)) for c in (0, 1, 9, 3, 4)]
    print(f"counters 0, 1, 9, 3, 4: {[(r.status.name, r.lost, r.accepted) for r in results]}")
    assert [r.status for r in results] == [E2EStatus.OK, E2EStatus.OK, E2EStatus.SEQUENCE_ERROR,
                                           E2EStatus.OK, E2EStatus.OK]
    assert [r.accepted for r in results] == [True, True, False, True, True]
    assert receiver.stats.lost == 7  # 9 - 1 - 1 frames skipped at the sequence error


def test_crc_error_keeps_the_reference_counter():
    """A corrupted frame is a lost frame: the next good one shows a jump of 2."""
    receiver = E2EReceiver(FrameId.VEH_DYN)
    frame = VehDyn(5.0, 0.0, 0.0)
    corrupted = bytearray(encode(frame, 4))
    corrupted[5] ^= 0x40
    results = [receiver.check(encode(frame, 3)), receiver.check(bytes(corrupted)),
               receiver.check(encode(frame, 5))]
    print(f"3, corrupted 4, 5: {[(r.status.name, r.lost) for r in results]}")
    assert [(r.status, r.lost) for r in results] == [
        (E2EStatus.OK, 0), (E2EStatus.CRC_ERROR, 0), (E2EStatus.LOST, 1)]


def test_wrong_length_is_discarded():
    receiver = E2EReceiver(FrameId.VEH_DYN)
    good = encode(VehDyn(1.0, 0.0, 0.0), 0)
    for length in range(0, 9):
        if length != 8:
            assert receiver.check(good[:length]).status is E2EStatus.WRONG_LENGTH
    assert receiver.check(good + b"\x00").status is E2EStatus.WRONG_LENGTH
    assert E2EReceiver(FrameId.HIL_SYNC).check(bytes(4)).status is E2EStatus.WRONG_LENGTH
    print(f"stats {receiver.stats.counts[E2EStatus.WRONG_LENGTH]} WRONG_LENGTH, "
          f"{receiver.stats.e2e_errors} E2E errors")
    assert receiver.stats.e2e_errors == 9 and not receiver.synchronised


TICKS = [
    (0, E2EStatus.OK), (5, E2EStatus.OK), (25, E2EStatus.OK), (0xFFFFFFFF, E2EStatus.OK),
    (0xFFFFFFFA, E2EStatus.OK),  # 4294967290 is a multiple of 5
    (1, E2EStatus.BAD_TICK), (7, E2EStatus.BAD_TICK), (0xFFFFFFFE, E2EStatus.BAD_TICK),
]


def test_hil_tick_must_be_multiple_of_5_or_handshake():
    for tick, status in TICKS:
        for frame in (HilSync(tick), HilSyncAck(tick)):
            receiver = E2EReceiver(frame.FRAME_ID)
            result = receiver.check(encode(frame))
            assert result.status is status and result.accepted == (status is E2EStatus.OK)
            assert receiver.stats.e2e_errors == (status is E2EStatus.BAD_TICK)
        print(f"TICK {tick}: {result.status.name}")


def test_hil_frames_may_repeat_without_counter():
    """No CNT on HIL frames: a repeated TICK is the ECU's business, not an E2E error."""
    receiver = E2EReceiver(FrameId.HIL_SYNC)
    statuses = [receiver.check(encode(HilSync(10))).status for _ in range(3)]
    print(f"TICK 10 three times: {[s.name for s in statuses]}")
    assert statuses == [E2EStatus.OK] * 3


def test_monitor_routes_by_id_and_counts_unknown():
    monitor = E2EMonitor()
    sender = FrameSender()
    results = [
        monitor.check(FrameId.VEH_DYN, sender.encode(VehDyn(1.0, 0.0, 0.0))),
        monitor.check(FrameId.VEH_POSE_XY, sender.encode(VehPoseXY(1.0, 0.0))),
        monitor.check(FrameId.VEH_DYN, sender.encode(VehDyn(1.0, 0.0, 0.0))),
        monitor.check(0x123, bytes(8)),
        monitor.check(FrameId.HIL_SYNC, encode(HilSync(3))),
    ]
    print(f"monitor: {[r.status.name for r in results]}; stats {monitor.stats}")
    assert [r.status for r in results] == [E2EStatus.OK, E2EStatus.OK, E2EStatus.OK,
                                           E2EStatus.UNKNOWN_ID, E2EStatus.BAD_TICK]
    assert monitor.stats.counts[E2EStatus.UNKNOWN_ID] == 1
    assert monitor.stats.e2e_errors == 1
    assert monitor.receiver(FrameId.VEH_DYN).stats.counts[E2EStatus.OK] == 2
    assert set(monitor.receivers) == set(FrameId)
    with pytest.raises(UnknownFrameError):
        monitor.receiver(0x123)
    with pytest.raises(UnknownFrameError):
        E2EReceiver(0x7FF)
    monitor.reset()
    assert not monitor.receiver(FrameId.VEH_DYN).synchronised


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.sampled_from(sorted(FrameId)), st.integers(0, 0x7FF)),
                          st.binary(min_size=0, max_size=8)),
                min_size=1, max_size=20))
def test_monitor_never_raises_on_arbitrary_frames(frames):
    monitor = E2EMonitor()
    for arbitration_id, data in frames:
        result = monitor.check(arbitration_id, data)
        assert isinstance(result.status, E2EStatus)
        assert result.accepted == (result.status in (E2EStatus.OK, E2EStatus.LOST))
        assert 0 <= result.lost <= 14
    assert monitor.stats.total == len(frames)


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(sorted(FrameId)), st.binary(min_size=8, max_size=8),
       st.lists(st.integers(0, 15), min_size=1, max_size=30))
def test_receiver_never_raises_and_counts_add_up(frame_id, payload, counters):
    """Random valid-CRC frames with random counters: totals and lost counts consistent."""
    receiver = E2EReceiver(frame_id)
    sender_frames = {
        FrameId.VEH_DYN: VehDyn(1.0, 2.0, 0.1), FrameId.VEH_POSE_XY: VehPoseXY(1.0, 2.0),
        FrameId.VEH_POSE_YAW: VehPoseYaw(0.1, 0.0, 0.0), FrameId.PLANNER_REQ: PlannerReq(True, 5.0, 0),
        FrameId.STEER_TORQUE_CMD: SteerTorqueCmd(CtrlMode.STANDBY, False, 0.0, 0.0),
        FrameId.CTRL_DIAG: CtrlDiag(QpStatus.NOT_RUN, 0, 0, 0, 0, 0),
    }
    lost = 0
    for counter in counters:
        data = encode(sender_frames[frame_id], counter) if frame_id in sender_frames else payload
        lost += receiver.check(data).lost
    receiver.check(payload)
    assert receiver.stats.total == len(counters) + 1
    assert receiver.stats.lost >= lost


def test_unusual_inputs_do_not_raise():
    monitor = E2EMonitor()
    odd = [(-1, bytes(8)), (1 << 40, bytes(8)), (FrameId.VEH_DYN, None),
           (FrameId.VEH_DYN, "abcdefgh"), (FrameId.VEH_DYN, memoryview(bytes(8))),
           (FrameId.VEH_DYN, bytearray(encode(VehDyn(0.0, 0.0, 0.0), 0))), ("0x100", bytes(8))]
    results = [monitor.check(arbitration_id, data).status.name for arbitration_id, data in odd]
    print(f"odd inputs: {results}")
    assert results == ["UNKNOWN_ID", "UNKNOWN_ID", "WRONG_LENGTH", "WRONG_LENGTH",
                       "CRC_ERROR", "OK", "UNKNOWN_ID"]

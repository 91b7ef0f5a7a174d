"""encode / decode / FrameSender against the contract: round trips at zero and at the
representable limits, saturation, refused values, and golden frames worked out by hand."""
from __future__ import annotations

import dataclasses
import math
import typing
from enum import IntEnum

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from can_defs import (FRAME_CLASSES, CtrlDiag, CtrlMode, DecodeError, EncodeError,
                      FrameId, FrameLengthError, FrameSender, HilSync, HilSyncAck,
                      PlannerReq, QpStatus, SteerTorqueCmd, UndefinedValueError,
                      UnknownFrameError, VehDyn, VehPoseXY, VehPoseYaw, decode, encode,
                      load_database)


def _signal(frame_class: type, field_name: str):
    message = load_database().get_message_by_frame_id(int(frame_class.FRAME_ID))
    return message.get_signal_by_name(field_name.upper())


def _frame_at(frame_class: type, where: str):
    """A frame with every numeric field at zero, at its minimum or at its maximum
    (representable limits, from the DBC); enums and bools at their first/last value."""
    hints = typing.get_type_hints(frame_class)
    kwargs = {}
    for field in dataclasses.fields(frame_class):
        hint, signal = hints[field.name], _signal(frame_class, field.name)
        if isinstance(hint, type) and issubclass(hint, IntEnum):
            members = list(hint)
            kwargs[field.name] = {"zero": members[0], "min": members[0], "max": members[-1]}[where]
        elif hint is bool:
            kwargs[field.name] = where == "max"
        else:
            value = {"zero": 0, "min": signal.minimum, "max": signal.maximum}[where]
            kwargs[field.name] = hint(value)
    return frame_class(**kwargs)


def _assert_frames_equal(decoded, expected, tolerance_lsb: float = 0.5) -> float:
    """Field-wise equality, floats within `tolerance_lsb` of the signal's factor.
    Returns the largest float difference found."""
    assert type(decoded) is type(expected)
    worst = 0.0
    for field in dataclasses.fields(expected):
        got, want = getattr(decoded, field.name), getattr(expected, field.name)
        if isinstance(want, float):
            factor = _signal(type(expected), field.name).scale
            difference = abs(got - want)
            worst = max(worst, difference)
            assert difference <= tolerance_lsb * factor + 1e-12, (field.name, got, want)
        else:
            assert got == want and type(got) is type(want), (field.name, got, want)
    return worst


@pytest.mark.parametrize("where", ["zero", "min", "max"])
def test_every_frame_round_trips_at_zero_and_limits(where):
    for frame_id, frame_class in FRAME_CLASSES.items():
        frame = _frame_at(frame_class, where)
        payload = encode(frame, counter=7)
        decoded = decode(frame_id, payload)
        worst = _assert_frames_equal(decoded.frame, frame, tolerance_lsb=1e-6)
        print(f"{frame_id.name} at {where}: {payload.hex()} -> {decoded.frame}, "
              f"max |diff| {worst:.1e}")
        assert len(payload) == 8
        assert decoded.crc_ok
        assert decoded.counter == (None if frame_id in (FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK) else 7)


def test_out_of_range_values_saturate_to_the_representable_range():
    for frame_id, frame_class in FRAME_CLASSES.items():
        hints = typing.get_type_hints(frame_class)
        for field in dataclasses.fields(frame_class):
            if hints[field.name] not in (int, float):
                continue
            signal = _signal(frame_class, field.name)
            for beyond, limit in ((signal.maximum + 1000 * signal.scale + 1, signal.maximum),
                                  (signal.minimum - 1000 * signal.scale - 1, signal.minimum),
                                  (1e300, signal.maximum), (-1e300, signal.minimum)):
                frame = dataclasses.replace(_frame_at(frame_class, "zero"),
                                            **{field.name: hints[field.name](beyond)})
                got = getattr(decode(frame_id, encode(frame)).frame, field.name)
                assert math.isclose(got, limit, rel_tol=1e-12, abs_tol=1e-12), (field.name, beyond, got)
            print(f"{frame_id.name}.{signal.name}: beyond limits -> "
                  f"[{signal.minimum}, {signal.maximum}]")


def test_steer_command_is_not_clipped_to_the_actuator_limit():
    """+-0.3 rad is the controller's and actuator's limit, not the field's: 0.5 rad is
    sent as 0.5 rad (the plant saturates it)."""
    frame = SteerTorqueCmd(CtrlMode.ACTIVE, True, 0.5, 0.0)
    got = decode(FrameId.STEER_TORQUE_CMD, encode(frame)).frame.steer_angle_cmd
    print(f"steer_angle_cmd 0.5 -> {got}")
    assert got == pytest.approx(0.5, abs=5e-5)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_refused(bad):
    refused = 0
    for frame_class in FRAME_CLASSES.values():
        hints = typing.get_type_hints(frame_class)
        for field in dataclasses.fields(frame_class):
            if hints[field.name] not in (int, float):
                continue
            frame = dataclasses.replace(_frame_at(frame_class, "zero"), **{field.name: bad})
            with pytest.raises(EncodeError, match=field.name.upper()):
                encode(frame)
            refused += 1
    print(f"{bad}: refused in {refused} numeric fields")
    assert refused == 19  # every int and float field of the eight frames


def test_bad_types_enum_values_and_counters_are_refused():
    cases = {
        "ctrl_mode 6": (SteerTorqueCmd(6, True, 0.0, 0.0), 0),
        "qp_status 7": (CtrlDiag(7, 0, 0, 0, 0, 0), 0),
        "string vx": (VehDyn("fast", 0.0, 0.0), 0),
        "numeric string vx": (VehDyn("1.5", 0.0, 0.0), 0),
        "bool vx": (VehDyn(True, 0.0, 0.0), 0),
        "array cmd_valid": (SteerTorqueCmd(CtrlMode.ACTIVE, np.array([1, 0]), 0.0, 0.0), 0),
        "cmd_valid 2": (SteerTorqueCmd(CtrlMode.ACTIVE, 2, 0.0, 0.0), 0),
        "counter 16": (VehDyn(0.0, 0.0, 0.0), 16),
        "counter -1": (VehDyn(0.0, 0.0, 0.0), -1),
        "not a frame": (object(), 0),
    }
    for name, (frame, counter) in cases.items():
        with pytest.raises(EncodeError) as error:
            encode(frame, counter)
        print(f"{name}: EncodeError({error.value})")


def test_numpy_scalars_and_plain_ints_are_accepted():
    frame = VehDyn(np.float64(1.5), np.float32(-0.25), 0)
    decoded = decode(FrameId.VEH_DYN, encode(frame)).frame
    diag = decode(FrameId.CTRL_DIAG, encode(CtrlDiag(0, np.int64(1200), 1500.4, np.float32(3.0),
                                                     0, np.uint8(2)))).frame
    print(f"{frame} -> {decoded}; {diag}")
    assert (decoded.vx, decoded.vy, decoded.yaw_rate) == (1.5, -0.25, 0.0)
    assert diag.qp_status is QpStatus.SOLVED and diag.solve_time_us == 1200
    assert diag.cycle_time_us == 1500 and diag.qp_iter == 3 and diag.faults == 2
    command = decode(FrameId.STEER_TORQUE_CMD,
                     encode(SteerTorqueCmd(2, np.bool_(True), 0.0, 0.0))).frame
    assert command.ctrl_mode is CtrlMode.ACTIVE and command.cmd_valid is True


def test_decode_errors_are_typed():
    with pytest.raises(UnknownFrameError):
        decode(0x7FF, bytes(8))
    with pytest.raises(FrameLengthError):
        decode(FrameId.VEH_DYN, bytes(7))
    # CTRL_MODE = 6 (bits 12..14 = 110) with a correct CRC: a sender bug, named.
    payload = bytearray(encode(SteerTorqueCmd(CtrlMode.INIT, False, 0.0, 0.0)))
    payload[1] |= 6 << 4
    payload[0] = _bitwise_crc(bytes([0x00, 0x02]) + bytes(payload[1:]))
    with pytest.raises(UndefinedValueError, match="CTRL_MODE") as error:
        decode(FrameId.STEER_TORQUE_CMD, bytes(payload))
    print(f"undefined CTRL_MODE: {error.value}")


def test_decode_reports_wrong_crc_without_raising():
    payload = bytearray(encode(VehDyn(10.0, 0.1, 0.01), counter=4))
    payload[3] ^= 0x01
    decoded = decode(FrameId.VEH_DYN, bytes(payload))
    print(f"corrupted VEH_DYN: crc_ok={decoded.crc_ok}, counter={decoded.counter}")
    assert decoded.crc_ok is False and decoded.counter == 4


def test_frame_sender_counts_per_id_mod_16():
    sender = FrameSender()
    counters = [decode(FrameId.VEH_DYN, sender.encode(VehDyn(0.0, 0.0, 0.0))).counter
                for _ in range(18)]
    planner = decode(FrameId.PLANNER_REQ, sender.encode(PlannerReq(False, 0.0, 0))).counter
    print(f"VEH_DYN counters {counters}; first PLANNER_REQ {planner}")
    assert counters == list(range(16)) + [0, 1]
    assert planner == 0
    with pytest.raises(EncodeError):
        sender.encode(VehDyn(math.nan, 0.0, 0.0))
    assert sender.next_counter(FrameId.VEH_DYN) == 2, "a refused frame must not use a counter"
    assert decode(FrameId.HIL_SYNC, sender.encode(HilSync(5))).counter is None
    sender.reset()
    assert sender.next_counter(FrameId.VEH_DYN) == 0


# ---------------------------------------------------------------------------------------
# Golden frames, worked out by hand from the contract table.
#
# Layout reminders (little-endian, DBC @1): a signal with start bit s and length n holds
# raw value bits 0..n-1 in payload bits s..s+n-1, where payload bit k is bit (k % 8) of
# byte k // 8. So a 16-bit signal at start 16 is byte 2 (low) and byte 3 (high).
# Signed raw values are two's complement: raw < 0 -> raw + 2**n.
# Byte 0 = CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xorout 0xFF, no reflection) over
# [ID low byte, ID high byte, payload bytes 1..7], computed below by _bitwise_crc, which
# is written here independently of can_defs.crc.


def _bitwise_crc(data: bytes) -> int:
    register = 0xFF
    for byte in data:
        for bit in range(7, -1, -1):  # MSB first: no reflection
            feedback = ((register >> 7) & 1) ^ ((byte >> bit) & 1)
            register = ((register << 1) & 0xFF) ^ (0x1D if feedback else 0)
    return register ^ 0xFF


GOLDEN = [
    # VEH_DYN (0x100), CNT 3: vx 12.34 m/s, vy -0.5 m/s, yaw_rate -0.1234 rad/s
    #   byte 1: CNT 3 in bits 8..11, bits 12..15 reserved 0            -> 0x03
    #   VX raw 12.34 / 0.01 = 1234 = 0x04D2                             -> bytes 2,3 = D2 04
    #   VY raw -0.5 / 0.001 = -500 -> 65536 - 500 = 65036 = 0xFE0C      -> bytes 4,5 = 0C FE
    #   YAW_RATE raw -0.1234 / 0.0001 = -1234 -> 64302 = 0xFB2E         -> bytes 6,7 = 2E FB
    #   CRC over 00 01 | 03 D2 04 0C FE 2E FB                           -> 0x60
    (VehDyn(12.34, -0.5, -0.1234), 3, bytes.fromhex("60 03 D2 04 0C FE 2E FB")),
    # VEH_POSE_XY (0x101), CNT 9: pos_x 1234.567 m, pos_y -0.001 m
    #   byte 1 = 0x09
    #   POS_X raw 1234567 = 0x12D687 (24 bit)                           -> bytes 2,3,4 = 87 D6 12
    #   POS_Y raw -1 -> 2**24 - 1 = 0xFFFFFF                            -> bytes 5,6,7 = FF FF FF
    #   CRC over 01 01 | 09 87 D6 12 FF FF FF                           -> 0x1C
    (VehPoseXY(1234.567, -0.001), 9, bytes.fromhex("1C 09 87 D6 12 FF FF FF")),
    # VEH_POSE_YAW (0x102), CNT 14: yaw -3.1416 rad, steer 0.05 rad, torque -1200 N m
    #   byte 1 = 0x0E
    #   YAW raw -31416 -> 65536 - 31416 = 34120 = 0x8548                -> bytes 2,3 = 48 85
    #   STEER_ANGLE raw 500 = 0x01F4                                    -> bytes 4,5 = F4 01
    #   DRIVE_TORQUE raw -12000 -> 53536 = 0xD120                       -> bytes 6,7 = 20 D1
    #   CRC over 02 01 | 0E 48 85 F4 01 20 D1                           -> 0xD1
    (VehPoseYaw(-3.1416, 0.05, -1200.0), 14, bytes.fromhex("D1 0E 48 85 F4 01 20 D1")),
    # PLANNER_REQ (0x110), CNT 5: engage 1, target_speed 13.89 m/s, path_id 2
    #   byte 1: CNT 5 | ENGAGE (bit 12 = byte 1 bit 4) 0x10             -> 0x15
    #   TARGET_SPEED raw 1389 = 0x056D                                  -> bytes 2,3 = 6D 05
    #   PATH_ID 2                                                       -> byte 4 = 02
    #   CRC over 10 01 | 15 6D 05 02 00 00 00                           -> 0x79
    (PlannerReq(True, 13.89, 2), 5, bytes.fromhex("79 15 6D 05 02 00 00 00")),
    # STEER_TORQUE_CMD (0x200), CNT 15: ACTIVE (2), cmd_valid 1, steer -0.3 rad, 250.5 N m
    #   byte 1: CNT 15 = 0x0F | CTRL_MODE 2 << 4 = 0x20 | CMD_VALID bit 15 = 0x80 -> 0xAF
    #   STEER_ANGLE_CMD raw -3000 -> 62536 = 0xF448                     -> bytes 2,3 = 48 F4
    #   DRIVE_TORQUE_CMD raw 2505 = 0x09C9                              -> bytes 4,5 = C9 09
    #   CRC over 00 02 | AF 48 F4 C9 09 00 00                           -> 0x0F
    (SteerTorqueCmd(CtrlMode.ACTIVE, True, -0.3, 250.5), 15, bytes.fromhex("0F AF 48 F4 C9 09 00 00")),
    # CTRL_DIAG (0x201), CNT 0: NOT_RUN (15), 1500 us, 2600 us, 25 iter, 2 overruns, faults 0b0110
    #   byte 1: CNT 0 | QP_STATUS 15 << 4                               -> 0xF0
    #   SOLVE_TIME_US 1500 = 0x05DC -> DC 05; CYCLE_TIME_US 2600 = 0x0A28 -> 28 0A
    #   QP_ITER 25 = 0x19; byte 7: OVERRUNS 2 (bits 56..59) | FAULTS 6 << 4 -> 0x62
    #   CRC over 01 02 | F0 DC 05 28 0A 19 62                           -> 0xEF
    (CtrlDiag(QpStatus.NOT_RUN, 1500, 2600, 25, 2, 6), 0, bytes.fromhex("EF F0 DC 05 28 0A 19 62")),
    # HIL_SYNC (0x080): TICK 125 = 0x7D in bytes 0..3, no CRC/CNT
    (HilSync(125), 0, bytes.fromhex("7D 00 00 00 00 00 00 00")),
    # HIL_SYNC_ACK (0x081): handshake TICK 0xFFFFFFFF
    (HilSyncAck(0xFFFFFFFF), 0, bytes.fromhex("FF FF FF FF 00 00 00 00")),
]


@pytest.mark.parametrize("frame, counter, expected", GOLDEN,
                         ids=[type(g[0]).__name__ for g in GOLDEN])
def test_golden_frames(frame, counter, expected):
    frame_id = int(type(frame).FRAME_ID)
    if frame_id not in (FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK):
        crc = _bitwise_crc(bytes([frame_id & 0xFF, frame_id >> 8]) + expected[1:])
        assert crc == expected[0], f"hand-written CRC 0x{expected[0]:02X}, bitwise 0x{crc:02X}"
    payload = encode(frame, counter)
    decoded = decode(frame_id, expected)
    print(f"{type(frame).__name__}: encode {payload.hex(' ')}, by hand {expected.hex(' ')}; "
          f"decode -> {decoded}")
    assert payload == expected
    assert decoded.crc_ok
    assert decoded.counter == (None if frame_id < 0x100 else counter)
    _assert_frames_equal(decoded.frame, frame, tolerance_lsb=1e-6)


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.sampled_from(sorted(FrameId)), st.integers(0, 0x7FF)),
       st.binary(min_size=0, max_size=8))
def test_decode_raises_only_typed_errors(arbitration_id, data):
    try:
        decoded = decode(arbitration_id, data)
    except (UnknownFrameError, FrameLengthError, UndefinedValueError):
        return
    assert len(data) == 8 and arbitration_id in FRAME_CLASSES
    assert isinstance(decoded.crc_ok, bool)


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(sorted(FRAME_CLASSES)), st.binary(min_size=8, max_size=8))
def test_decode_of_known_ids_raises_only_decode_errors(arbitration_id, data):
    try:
        decode(arbitration_id, data)
    except DecodeError as error:
        assert isinstance(error, UndefinedValueError)


@settings(max_examples=200, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(-40.0, 40.0),
       st.floats(-3.0, 3.0), st.integers(0, 15))
def test_encode_arbitrary_floats_saturates_or_refuses(vx, vy, yaw_rate, counter):
    frame = VehDyn(vx, vy, yaw_rate)
    if not math.isfinite(vx):
        with pytest.raises(EncodeError):
            encode(frame, counter)
        return
    decoded = decode(FrameId.VEH_DYN, encode(frame, counter))
    assert decoded.crc_ok and decoded.counter == counter
    assert abs(decoded.frame.vx - min(max(vx, -327.68), 327.67)) <= 0.005 + 1e-9
    assert abs(decoded.frame.vy - min(max(vy, -32.768), 32.767)) <= 0.0005 + 1e-9
    assert abs(decoded.frame.yaw_rate - yaw_rate) <= 0.00005 + 1e-9

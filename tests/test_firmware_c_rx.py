"""The C receive path against the Python contract code, fuzzed with hypothesis through
libecu.so (``make firmware-asan`` runs this on the sanitized build too): the E2E verdicts
of ``can_defs.e2e.E2EMonitor`` and the values of ``can_defs.codec.decode``
(firmware/src/ecu_rx.c), and whole frame sequences through the ECU node
(firmware/src/ecu_node.c)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from can_defs.codec import decode
from can_defs.crc import e2e_crc
from can_defs.e2e import E2EMonitor
from can_defs.frames import FrameId
from test_firmware_c_core import native  # noqa: F401 (the fixture: libecu.so built and loaded)

CONTRACT_IDS = [int(f) for f in FrameId]
RECEIVED = [FrameId.VEH_DYN, FrameId.VEH_POSE_XY, FrameId.VEH_POSE_YAW, FrameId.PLANNER_REQ,
            FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK]


@st.composite
def frames(draw) -> tuple[int, bytes]:
    """A frame as a receiver may see it: mostly well-formed (good CRC, a counter near the
    last), some with a bad CRC, a wrong length, a foreign ID or a bad TICK."""
    frame_id = draw(st.one_of(st.sampled_from(CONTRACT_IDS), st.integers(0, 0x7FF)))
    length = draw(st.one_of(st.just(8), st.integers(0, 12)))
    payload = bytearray(draw(st.binary(min_size=length, max_size=length)))
    if length == 8 and draw(st.booleans()):
        payload[1] = (payload[1] & 0xF0) | draw(st.integers(0, 3))  # counters close together
        payload[0] = e2e_crc(frame_id, bytes(payload))
    if length == 8 and frame_id in (FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK) and draw(st.booleans()):
        payload[0:4] = draw(st.sampled_from([0, 5, 25, 0xFFFFFFFF, 7])).to_bytes(4, "little")
    return frame_id, bytes(payload)


@settings(max_examples=300, deadline=None)
@given(st.lists(frames(), min_size=1, max_size=40))
def test_e2e_verdicts_equal_python(native, sequence) -> None:
    """Every frame of any sequence gets the Python receiver's verdict, lost count and use."""
    monitor, c_monitor = E2EMonitor(), native.NativeE2EMonitor()
    for frame_id, data in sequence:
        expected = monitor.check(frame_id, data)
        assert c_monitor.check(frame_id, data) == (expected.status.name, expected.lost, expected.accepted)


def test_crc_check_value(native) -> None:
    """The contract's CRC of a known frame, equal to can_defs.crc's."""
    data = bytes(range(8))
    assert native.e2e_crc(0x100, data) == e2e_crc(0x100, data)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(RECEIVED), st.binary(min_size=8, max_size=8))
def test_decoded_values_equal_python(native, frame_id: FrameId, data: bytes) -> None:
    """The generated C codecs decode every payload to can_defs' physical values."""
    frame = decode(frame_id, data).frame
    values = tuple(float(v) for v in dataclasses.astuple(frame))
    assert native.decode_values(frame_id, data) == values
    assert native.decode_values(0x7FF, data) is None


@st.composite
def cycles(draw) -> list[tuple[int, bytes, bool]]:
    """Up to 30 lockstep ticks of plant and planner frames, mostly well-formed (so that the
    node reaches ACTIVE), with mutations: bits flipped, frames dropped or duplicated,
    foreign frames, wrong lengths, odd TICKs (repeated, backwards, far ahead, the
    handshake again) and non-classic frames."""
    from can_defs.codec import encode
    from can_defs.frames import HilSync, PlannerReq, VehDyn, VehPoseXY, VehPoseYaw

    frames: list[tuple[int, bytes, bool]] = [(FrameId.HIL_SYNC, encode(HilSync(0xFFFFFFFF)), True)]
    tick, counter, planner_counter = 0, 0, 0
    x = draw(st.floats(-5.0, 60.0))
    for _ in range(draw(st.integers(1, 30))):
        for _ in range(draw(st.sampled_from([1, 1, 1, 2, 0]))):
            vx = draw(st.sampled_from([10.0, 10.0, 10.0, 0.0, -100.0, 400.0]))
            x += 0.05
            plant = [VehDyn(vx=vx, vy=draw(st.floats(-1.0, 1.0)), yaw_rate=draw(st.floats(-0.5, 0.5))),
                     VehPoseXY(pos_x=x, pos_y=draw(st.floats(-1.0, 1.0))),
                     VehPoseYaw(yaw=draw(st.floats(-0.3, 0.3)), steer_angle=draw(st.floats(-0.3, 0.3)),
                                drive_torque=draw(st.floats(-3000.0, 2000.0)))]
            frames += [(f.FRAME_ID, encode(f, counter), True) for f in plant]
            counter = (counter + draw(st.sampled_from([1, 1, 1, 2, 0, 5]))) % 16
        if draw(st.booleans()):
            request = PlannerReq(engage=draw(st.sampled_from([True, True, True, False])),
                                 target_speed=draw(st.floats(0.0, 30.0)), path_id=draw(st.sampled_from([0, 0, 0, 7])))
            frames.append((FrameId.PLANNER_REQ, encode(request, planner_counter), True))
            planner_counter = (planner_counter + draw(st.sampled_from([1, 1, 1, 0, 4]))) % 16
        for _ in range(draw(st.sampled_from([0] * 6 + [1, 2]))):  # mutations of what was queued
            if not frames:  # every queued frame dropped: nothing to pick (an empty range is invalid)
                break
            i = draw(st.integers(0, len(frames) - 1))
            frame_id, data, kind = frames[i]
            action = draw(st.sampled_from(["flip", "drop", "duplicate", "length", "foreign", "kind"]))
            if action == "flip" and data:
                bit = draw(st.integers(0, 8 * len(data) - 1))
                data = data[:bit // 8] + bytes([data[bit // 8] ^ (1 << bit % 8)]) + data[bit // 8 + 1:]
                frames[i] = (frame_id, data, kind)
            elif action == "drop":
                frames.pop(i)
            elif action == "duplicate":
                frames.insert(i, frames[i])
            elif action == "length":
                frames[i] = (frame_id, data[:draw(st.integers(0, 7))], kind)
            elif action == "foreign":
                frames.insert(i, (draw(st.integers(0, 0x7FF)), draw(st.binary(max_size=8)), True))
            else:
                frames[i] = (frame_id, data, False)
        tick += draw(st.sampled_from([5] * 30 + [0, -5, 200, 7]))
        tick_value = draw(st.sampled_from([tick % 2**32] * 40 + [0xFFFFFFFF]))
        frames.append((FrameId.HIL_SYNC, encode(HilSync(tick_value)) if tick_value % 5 == 0 or tick_value ==
                       0xFFFFFFFF else tick_value.to_bytes(4, "little") + bytes(4), True))
    return frames


@settings(max_examples=200, deadline=None)
@given(cycles())
def test_fuzz_node_sends_only_commands_within_the_contract(native, core_on_dlc, frames) -> None:
    """Any frame sequence through the C node (sample assembly, E2E, lockstep, modes, guard):
    no crash (nor a sanitizer finding under make firmware-asan), and every command it sends
    is a well-formed STEER_TORQUE_CMD within the limits, valid only in ACTIVE, DEGRADED or
    SAFE_STOP."""
    node = native.NativeNode()
    for frame_id, data, kind in frames:
        node.receive(frame_id, data, kind)
    modes = {int(decode(i, d).frame.ctrl_mode) for i, d in node.sent if i == FrameId.STEER_TORQUE_CMD}
    event(f"modes {sorted(modes)}")
    for frame_id, data in node.sent:
        assert len(data) == 8
        if frame_id == FrameId.STEER_TORQUE_CMD:
            decoded = decode(frame_id, data)
            assert decoded.crc_ok
            command = decoded.frame
            assert abs(command.steer_angle_cmd) <= 0.3 and abs(command.drive_torque_cmd) <= 3000.0
            assert not command.cmd_valid or int(command.ctrl_mode) in (2, 3, 4)
        else:
            assert frame_id in (FrameId.CTRL_DIAG, FrameId.HIL_SYNC_ACK)


@pytest.fixture(scope="module")
def core_on_dlc(native):
    """LMPC's core with the double lane change as PATH_ID 0 (the node's path)."""
    core = native.NativeController("lmpc")
    core.load_path_file(Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv")
    return core


def test_timing_record_keeps_the_last_tasks_oldest_first(native, core_on_dlc, tmp_path: Path) -> None:
    """More control tasks than the record holds (65,536): the .npz keeps the newest, oldest
    first (the ring is unrolled in place), and counts them all."""
    import numpy as np

    from can_defs.codec import encode
    from can_defs.frames import HilSync
    from firmware_sim.timing import load_timing

    node = native.NativeNode()
    node.receive(FrameId.HIL_SYNC, encode(HilSync(0xFFFFFFFF)))
    tasks = 65_536 + 1_000
    for k in range(tasks):
        node.receive(FrameId.HIL_SYNC, encode(HilSync(25 * k)))
    node.save_timing(tmp_path / "timing.npz")
    record = load_timing(tmp_path / "timing.npz")
    start = record.columns["start_time"]
    assert record.count == tasks and start.size == 65_536
    np.testing.assert_allclose(start, 0.025 * np.arange(tasks - 65_536, tasks))
    assert np.all(np.isnan(record.columns["release_jitter"]))  # lockstep: no release time

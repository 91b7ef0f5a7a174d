"""The C core's receive path (firmware/src/ecu_rx.c) against the Python contract code:
the E2E verdicts of ``can_defs.e2e.E2EMonitor`` and the values of ``can_defs.codec.decode``,
fuzzed with hypothesis through libecu.so (``make firmware-asan`` runs this on the
sanitized build too)."""
from __future__ import annotations

import dataclasses

from hypothesis import given, settings
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

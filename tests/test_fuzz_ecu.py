"""Fuzzing the ECU's receive path: arbitrary frames (any 11-bit ID, length 0-8, any bytes,
CAN FD / extended / remote / error frames, also copies of good contract frames and the
handshake in those kinds, which the contract's revision 2 says to ignore), well-formed plant and planner frames with extreme values
and broken counters, single bit flips of good frames and HIL_SYNC at any TICK, in any
order, straight into ``Ecu.handle_message`` (no threads, no bus: a list collects what the
ECU sends).

Never an exception inside the node (it would log "unexpected error"); every HIL_SYNC the
contract says to answer is answered, in order, and nothing else; every STEER_TORQUE_CMD
decodes with a correct CRC, |steer| <= 0.3 rad, |torque| <= 3000 N m, CMD_VALID = 1 exactly
in ACTIVE / DEGRADED / SAFE_STOP and no drive torque in SAFE_STOP.

The law is a deliberately bad controller (`WildController`): its command is out of the
limits for large errors and it raises ZeroDivisionError at VX = 0, so the guard and the
fallback are fuzzed too (tests/test_ecu_fuzz.py covers garbage between regular lockstep
ticks over a real bus; this file covers the RX path itself, at volume).

Examples: 10,000 (fixed seed: ``derandomize``) in ``make test``; ``make fuzz`` sets
``FUZZ_EXAMPLES`` (default there 200,000).
"""
from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_defs.codec import decode, encode
from can_defs.crc import e2e_crc
from can_defs.frames import (HANDSHAKE_TICK, CtrlDiag, CtrlMode, FrameId, HilSync, HilSyncAck,
                             PlannerReq, SteerTorqueCmd, VehDyn, VehPoseXY, VehPoseYaw)
from controller.base import Command, SolverStatus, StepDebug, VehicleSample
from firmware_sim.config import EcuConfig
from firmware_sim.ecu import Ecu
from firmware_sim.modes import VALID_COMMAND_MODES
from hil.ecu_harness import ScriptedController

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "10000"))
STEER_LIMIT_RAD = 0.3
TORQUE_LIMIT_NM = 3000.0


@dataclass
class WildController(ScriptedController):
    """A law that misbehaves on odd inputs: out-of-limit commands for large errors,
    ZeroDivisionError at VX = 0, NaN for infinite ratios."""

    name: str = "wild"

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        steer = 3.0 * sample.yaw_rate - sample.y / sample.vx   # raises at vx == 0
        torque = 800.0 * (sample.target_speed - sample.vx)
        return Command(steer, torque), StepDebug(SolverStatus.SOLVED, 3, 1e-4)


@dataclass
class CaptureBus:
    """Stands in for the ECU's bus: keeps every frame sent."""

    sent: list[can.Message] = field(default_factory=list)

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        self.sent.append(message)

    def shutdown(self) -> None:
        pass


class _ErrorCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.unexpected: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "unexpected error" in record.getMessage():
            self.unexpected.append(record.getMessage())


# --- the scripts ---------------------------------------------------------------------------
#
# A script is decoded from one byte string that hypothesis draws (16 bytes per event):
# drawing one blob instead of a tree of strategies halves the cost of an example, and
# hypothesis still shrinks a failure to a short script. Byte 0 of each chunk picks the kind.

RX_IDS = [int(i) for i in (FrameId.HIL_SYNC, FrameId.VEH_DYN, FrameId.VEH_POSE_XY,
                           FrameId.VEH_POSE_YAW, FrameId.PLANNER_REQ)]
CHUNK = 16
MAX_EVENTS = 16
_SCALES = (0.0, 0.01, 1.0, 100.0, 1e4, 1e6)          # physical = int8 * scale
_COUNTER_STEPS = (1, 1, 1, 1, 0, 2, 3, 7)             # 0 repeats, 7 is a sequence error
_SYNC_STEPS = (0, 5, 5, 5, 10, 25, 25, 50, 200, -5, 1)
_FLAGS = ("data", "data", "data", "fd", "extended", "remote", "error", "fd")


def _int8(byte: int) -> int:
    return byte - 256 if byte > 127 else byte


def script_of(blob: bytes) -> list[tuple]:
    """Events of one example; kinds:

    - ``cycle``: a regular 25 ms period (plant set, engaged planner on PATH_ID 1,
      HIL_SYNC to the next multiple of 25) and ``quiet``: HIL_SYNC only, +25 / 50 / 125 ms.
      With them a random script gets to ACTIVE and out of it again (DEGRADED, SAFE_STOP,
      STANDBY) often enough to fuzz those modes;
    - ``raw``: any 11-bit ID (half of them the ECU's), 0-8 bytes, data / CAN FD /
      extended / remote / error frame (a quarter of the other kinds carry 8 bytes, on
      HIL_SYNC the handshake value: none of them may be answered or reset the ECU);
    - ``plant`` / ``planner``: well-formed frames, values from 0 to +-1.3e8 (saturated by
      the encoder), counters that repeat or jump, a plant frame left out (torn set);
    - ``flip``: the last good frame of an ID with one bit flipped;
    - ``sync``: HIL_SYNC a step from the last TICK (also backwards, not a multiple of 5)
      or at an absolute TICK.
    """
    events: list[tuple] = []
    for i in range(0, len(blob) - CHUNK + 1, CHUNK):
        c = blob[i:i + CHUNK]
        kind = c[0] % 9
        if kind in (0, 1):
            events.append(("cycle", (0.0, 0.2, -0.5, 3.0)[c[1] % 4]))
        elif kind == 2:
            events.append(("quiet", (25, 50, 125)[c[1] % 3]))
        elif kind in (3, 4):
            frame_id = RX_IDS[c[1] % 5] if c[2] < 128 else int.from_bytes(c[2:4], "little") & 0x7FF
            flags = _FLAGS[c[5] % len(_FLAGS)]
            if flags != "data" and c[6] % 4 == 0:
                # a look-alike: a good contract frame (or the handshake) in another kind
                payload = encode(HilSync(HANDSHAKE_TICK)) if frame_id == FrameId.HIL_SYNC \
                    else bytes(c[8:16])
                events.append(("raw", frame_id, payload, flags))
            else:
                events.append(("raw", frame_id, bytes(c[8:8 + c[4] % 9]), flags))
        elif kind == 5:
            scale = _SCALES[c[1] % len(_SCALES)]
            values = tuple(_int8(b) * scale for b in c[8:16])
            left_out = {RX_IDS[1 + c[3] % 6]} if c[3] % 6 < 3 else set()
            events.append(("plant", values, _COUNTER_STEPS[c[2] % 8], left_out))
        elif kind == 6:
            speed = _int8(c[2]) * _SCALES[c[3] % len(_SCALES)]
            path_id = 1 if c[4] < 200 else c[5]
            events.append(("planner", bool(c[1] & 1), speed, path_id, (1, 1, 1, 0, 5)[c[6] % 5]))
        elif kind == 7:
            events.append(("flip", RX_IDS[1 + c[1] % 4], c[2] % 64))
        else:
            absolute = c[1] % 16 == 0
            value = int.from_bytes(c[4:6], "little", signed=True) if absolute \
                else _SYNC_STEPS[c[2] % len(_SYNC_STEPS)]
            events.append(("sync", value, absolute))
    return events


scripts = st.binary(min_size=CHUNK * 3, max_size=CHUNK * MAX_EVENTS).map(script_of)


# --- the model of what the ECU must answer ------------------------------------------------


@functools.lru_cache(maxsize=4096)
def _encode(frame: object, counter: int) -> bytes:
    """``can_defs.codec.encode``, cached: the regular frames repeat (cantools is the cost)."""
    return encode(frame, counter)


class AckModel:
    """HIL_SYNC_ACKs the contract requires (handshake answered and resets; after it, a
    TICK that is a multiple of 5 and not older than the last is answered, repeats too)."""

    def __init__(self) -> None:
        self.synchronised = False
        self.last: int | None = None
        self.expected: list[int] = []

    def sync(self, data: bytes) -> None:
        if len(data) != 8:
            return
        tick = int.from_bytes(data[:4], "little")
        if tick == HANDSHAKE_TICK:
            self.synchronised, self.last = True, None
            self.expected.append(tick)
        elif tick % 5 == 0 and self.synchronised and (self.last is None or tick >= self.last):
            self.last = tick
            self.expected.append(tick)


class Driver:
    """Feeds events to one ECU and tracks what the contract says it must answer."""

    def __init__(self) -> None:
        self.bus = CaptureBus()
        self.ecu = Ecu(self.bus, "wild", {1: Path("one.csv")}, lockstep=True,  # type: ignore[arg-type]
                       config=EcuConfig(timing_capacity=64),
                       controller_factory=lambda name: WildController(),
                       path_loader=str)
        self.acks = AckModel()
        self.counters = {i: 0 for i in RX_IDS[1:]}
        self.last_good: dict[int, bytes] = {}
        self.tick = 0

    def send(self, frame_id: int, data: bytes, kind: str = "data") -> None:
        message = can.Message(arbitration_id=frame_id, data=data, dlc=len(data),
                              is_extended_id=kind == "extended", is_remote_frame=kind == "remote",
                              is_error_frame=kind == "error", is_fd=kind == "fd")
        if kind == "data" and frame_id == FrameId.HIL_SYNC:
            self.acks.sync(bytes(data))
        _STATS["kinds"][kind] = _STATS["kinds"].get(kind, 0) + 1
        if kind != "data" and frame_id == FrameId.HIL_SYNC and bytes(data) == _HANDSHAKE:
            _STATS["kinds"]["handshake look-alike"] = _STATS["kinds"].get("handshake look-alike", 0) + 1
        self.ecu.handle_message(message)

    def run(self, event: tuple) -> None:
        kind = event[0]
        if kind == "cycle":
            _, y = event
            self.run(("plant", (10.0, 0.0, 0.0, 5.0, y, 0.0, 0.0, 0.0), 1, set()))
            self.run(("planner", True, 10.0, 1, 1))
            self.run(("sync", 25 - self.tick % 25, False))
        elif kind == "quiet":
            self.run(("sync", event[1], False))
        elif kind == "raw":
            _, frame_id, data, flags = event
            self.send(frame_id, data, flags)
        elif kind == "plant":
            _, values, step, left_out = event
            vx, vy, yaw_rate, x, y, yaw, steer, torque = values
            frames = (VehDyn(vx, vy, yaw_rate), VehPoseXY(x, y), VehPoseYaw(yaw, steer, torque))
            counter = (self.counters[FrameId.VEH_DYN] + step) % 16
            for frame in frames:
                self.counters[frame.FRAME_ID] = counter
                data = _encode(frame, counter)
                self.last_good[frame.FRAME_ID] = data
                if frame.FRAME_ID not in left_out:
                    self.send(frame.FRAME_ID, data)
        elif kind == "planner":
            _, engage, speed, path_id, step = event
            counter = (self.counters[FrameId.PLANNER_REQ] + step) % 16
            self.counters[FrameId.PLANNER_REQ] = counter
            data = _encode(PlannerReq(engage, speed, path_id), counter)
            self.last_good[FrameId.PLANNER_REQ] = data
            self.send(FrameId.PLANNER_REQ, data)
        elif kind == "flip":
            _, frame_id, bit = event
            if frame_id in self.last_good:
                data = bytearray(self.last_good[frame_id])
                data[bit // 8] ^= 1 << (bit % 8)
                self.send(frame_id, bytes(data))
        else:
            _, value, absolute = event
            self.tick = value if absolute else self.tick + value
            self.send(FrameId.HIL_SYNC, _encode(HilSync(self.tick % (1 << 32)), 0))


def check_sent(sent: list[can.Message]) -> list[int]:
    """Assert every ECU frame is well-formed and every command valid; returns the ACK ticks."""
    acks = []
    for message in sent:
        data = bytes(message.data)
        assert len(data) == 8 and not message.is_extended_id
        frame = decode(message.arbitration_id, data)
        if message.arbitration_id != FrameId.HIL_SYNC_ACK:
            assert frame.crc_ok and data[0] == e2e_crc(message.arbitration_id, data)
        value = frame.frame
        if isinstance(value, HilSyncAck):
            acks.append(value.tick)
        elif isinstance(value, SteerTorqueCmd):
            assert value.cmd_valid == (value.ctrl_mode in VALID_COMMAND_MODES), value
            assert math.isfinite(value.steer_angle_cmd) and abs(value.steer_angle_cmd) <= STEER_LIMIT_RAD, value
            assert math.isfinite(value.drive_torque_cmd) and abs(value.drive_torque_cmd) <= TORQUE_LIMIT_NM, value
            if value.ctrl_mode is CtrlMode.SAFE_STOP:
                assert value.drive_torque_cmd <= 0.0, value
        else:
            assert isinstance(value, CtrlDiag), value
    return acks


_STATS: dict = {"examples": 0, "commands": 0, "valid_commands": 0, "modes": set(), "kinds": {}}
_HANDSHAKE = encode(HilSync(HANDSHAKE_TICK))


@pytest.mark.slow
@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(script=scripts)
def test_any_frames_never_break_the_rx_path(script):
    counter = _ErrorCounter()
    logger = logging.getLogger("firmware_sim")
    logger.addHandler(counter)
    try:
        driver = Driver()
        driver.send(FrameId.HIL_SYNC, encode(HilSync(HANDSHAKE_TICK)))
        for event in script:
            driver.run(event)
        driver.ecu.close()
    finally:
        logger.removeHandler(counter)
    assert not counter.unexpected, counter.unexpected[0]
    acks = check_sent(driver.bus.sent)
    assert acks == driver.acks.expected
    commands = [decode(m.arbitration_id, bytes(m.data)).frame for m in driver.bus.sent
                if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    _STATS["examples"] += 1
    _STATS["commands"] += len(commands)
    _STATS["valid_commands"] += sum(c.cmd_valid for c in commands)
    _STATS["modes"].update(c.ctrl_mode.name for c in commands)


def test_fuzz_reached_the_control_modes():
    """The fuzz above is only worth something if it drove the ECU into the modes that send
    valid commands; run after it (same module), it checks the coverage it recorded."""
    if _STATS["examples"] == 0:
        pytest.skip("the fuzz test did not run (deselected)")
    print(f"\nfuzz: {_STATS['examples']} examples, {_STATS['commands']} commands, "
          f"{_STATS['valid_commands']} with CMD_VALID = 1, modes {sorted(_STATS['modes'])}, "
          f"frames by kind {_STATS['kinds']}")
    assert {"STANDBY", "ACTIVE", "DEGRADED", "SAFE_STOP"} <= _STATS["modes"]
    assert _STATS["valid_commands"] > 0
    # contract rev. 2: the other frame kinds, and the handshake in them, were really sent
    assert {"data", "fd", "extended", "remote", "error", "handshake look-alike"} <= set(_STATS["kinds"])


def test_driver_reaches_active_and_checks_catch_a_bad_command():
    """The harness itself: a clean script reaches ACTIVE with valid commands, and the
    command check fails on a forged out-of-limit command (so it can fail)."""
    driver = Driver()
    driver.send(FrameId.HIL_SYNC, encode(HilSync(HANDSHAKE_TICK)))
    for t in range(0, 100, 5):
        if t % 10 == 0:
            driver.run(("plant", (10.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0), 1, set()))
        if t % 25 == 0:
            driver.run(("planner", True, 10.0, 1, 1))
        driver.run(("sync", t, True))
    acks = check_sent(driver.bus.sent)
    assert acks == driver.acks.expected == [HANDSHAKE_TICK] + list(range(0, 100, 5))
    modes = [decode(m.arbitration_id, bytes(m.data)).frame.ctrl_mode for m in driver.bus.sent
             if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    assert CtrlMode.ACTIVE in modes
    forged = can.Message(arbitration_id=int(FrameId.STEER_TORQUE_CMD), is_extended_id=False,
                         data=encode(SteerTorqueCmd(CtrlMode.ACTIVE, True, 0.31, 0.0), 0))
    with pytest.raises(AssertionError):
        check_sent([forged])

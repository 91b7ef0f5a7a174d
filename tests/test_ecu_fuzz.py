"""Garbage on the bus never breaks the ECU: random payloads (any length, any of the IDs it
receives) between lockstep ticks never raise inside the node, every tick is still ACKed,
and every command sent is within the limits."""
from __future__ import annotations

import logging
import math
import uuid
from pathlib import Path

import can
from can_defs.frames import FrameId, HilSyncAck
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.ecu import Ecu
from firmware_sim.modes import VALID_COMMAND_MODES
from hil.ecu_harness import PeerNodes, ScriptedController, commands, decode_messages, pump

RX_IDS = [FrameId.HIL_SYNC, FrameId.VEH_DYN, FrameId.VEH_POSE_XY, FrameId.VEH_POSE_YAW,
          FrameId.PLANNER_REQ, 0x7FF]
garbage = st.lists(st.tuples(st.sampled_from(RX_IDS), st.binary(min_size=0, max_size=8)),
                   max_size=6)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(per_tick=st.lists(garbage, min_size=12, max_size=12))
def test_random_frames_never_break_the_node(per_tick, caplog):
    channel = f"ecu-fuzz-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel) as ecu_bus, \
            can.Bus(interface="virtual", channel=channel) as peer_bus:
        ecu = Ecu(ecu_bus, "scripted", {1: Path("one.csv")}, lockstep=True,
                  controller_factory=lambda name: ScriptedController(gain=-0.5),
                  path_loader=str)
        peers = PeerNodes(peer_bus)
        peers.send_handshake()
        pump(ecu, ecu_bus)
        peers.received()
        sent = []
        caplog.clear()
        with caplog.at_level(logging.ERROR, logger="firmware_sim"):
            for index, junk in enumerate(per_tick):
                t = 5 * index
                if t % 10 == 0:
                    peers.send_plant(vx=10.0, y=float(index))
                if t % 25 == 0:
                    peers.send_planner()
                for frame_id, data in junk:
                    if frame_id != FrameId.HIL_SYNC:   # a random SYNC would be a new TICK
                        peers.send_raw(frame_id, data)
                peers.send_sync(t)
                pump(ecu, ecu_bus)
                sent += peers.received()
        ecu.close()
    unexpected = [r for r in caplog.records if "unexpected error" in r.getMessage()]
    assert not unexpected, unexpected[0].getMessage()
    acks = [f.tick for f in decode_messages(sent) if isinstance(f, HilSyncAck)]
    assert acks == [5 * i for i in range(12)]
    for command in commands(sent):
        assert math.isfinite(command.steer_angle_cmd) and abs(command.steer_angle_cmd) <= 0.3
        assert abs(command.drive_torque_cmd) <= 3000.0
        assert command.cmd_valid == (command.ctrl_mode in VALID_COMMAND_MODES)

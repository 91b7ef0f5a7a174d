"""A third-party node built from the DBC and the contract alone (cantools + python-can,
no can_defs codec) talks to can_defs over a python-can virtual bus, both ways."""
from __future__ import annotations

import can
import cantools

from can_defs import (DBC_PATH, CtrlMode, E2EMonitor, E2EStatus, FrameId, VehDyn, decode,
                      encode)

from contract_reference import crc8_sae_j1850_bitwise


def test_third_party_command_is_accepted_and_our_frames_decode_with_cantools():
    database = cantools.database.load_file(str(DBC_PATH))
    command = database.get_message_by_name("STEER_TORQUE_CMD")
    payload = bytearray(command.encode({
        "CRC": 0, "CNT": 3, "CTRL_MODE": "ACTIVE", "CMD_VALID": 1,
        "STEER_ANGLE_CMD": -0.1, "DRIVE_TORQUE_CMD": 100.0}))
    frame_id = command.frame_id
    payload[0] = crc8_sae_j1850_bitwise(bytes([frame_id & 0xFF, frame_id >> 8]) + payload[1:])

    with can.Bus(interface="virtual", channel="can_defs_interop") as third_party, \
            can.Bus(interface="virtual", channel="can_defs_interop") as our_node:
        third_party.send(can.Message(arbitration_id=frame_id, data=payload, is_extended_id=False))
        received = our_node.recv(timeout=1.0)
        our_node.send(can.Message(arbitration_id=FrameId.VEH_DYN, is_extended_id=False,
                                  data=encode(VehDyn(13.9, -0.21, 0.05), counter=9)))
        reply = third_party.recv(timeout=1.0)

    assert received is not None and reply is not None
    result = E2EMonitor().check(received.arbitration_id, bytes(received.data))
    decoded = decode(received.arbitration_id, bytes(received.data))
    print(f"third-party STEER_TORQUE_CMD {bytes(received.data).hex(' ')}: {result.status.name}, "
          f"{decoded.frame}")
    assert result.status is E2EStatus.OK
    assert decoded.frame.ctrl_mode is CtrlMode.ACTIVE and decoded.frame.cmd_valid
    assert abs(decoded.frame.steer_angle_cmd + 0.1) < 5e-5
    assert abs(decoded.frame.drive_torque_cmd - 100.0) < 0.05

    signals = database.decode_message(reply.arbitration_id, reply.data)
    crc = crc8_sae_j1850_bitwise(bytes([0x00, 0x01]) + bytes(reply.data[1:]))
    print(f"our VEH_DYN decoded by cantools: {signals}; CRC by third party 0x{crc:02X}")
    assert signals["CRC"] == crc and signals["CNT"] == 9
    assert abs(signals["VX"] - 13.9) < 0.005 and abs(signals["VY"] + 0.21) < 0.0005

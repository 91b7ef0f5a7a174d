"""A third-party plant, planner and time master written from docs/can-contract.md alone (raw
bytes with python-can, struct and bit arithmetic; no can_defs, no hil nodes) drives the
project's ECU. If the ECU needed anything beyond the contract, this test would not get it
to steer the car along the path.

The plant is a kinematic bicycle (wheelbase 2.7 m, drive force = torque / 0.3 m): not the
project's four-wheel plant, as a foreign HIL rig would not be.
"""
from __future__ import annotations

import math
import struct
import threading
from pathlib import Path

import can
import pytest

from contract_reference import crc8_sae_j1850_bitwise

PATH_FILE = Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"
HANDSHAKE = 0xFFFFFFFF


def protected(arbitration_id: int, counter: int, flags: int, body: bytes) -> bytes:
    """Byte 0 CRC, byte 1 CNT | flags << 4, bytes 2..7 ``body`` (6 bytes)."""
    assert len(body) == 6
    rest = bytes([(counter & 0x0F) | (flags & 0x0F) << 4]) + body
    crc = crc8_sae_j1850_bitwise(bytes([arbitration_id & 0xFF, arbitration_id >> 8]) + rest)
    return bytes([crc]) + rest


def sat(value: float, bits: int) -> int:
    low, high = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return max(low, min(high, round(value)))


def int24(value: int) -> bytes:
    return (value & 0xFFFFFF).to_bytes(3, "little")


def dlc_y(x: float) -> float:
    """The double lane change of the architecture spec, Y(X)."""
    z1 = 2.4 / 25 * (x - 27.19) - 1.2
    z2 = 2.4 / 21.95 * (x - 56.46) - 1.2
    return 4.05 / 2 * (1 + math.tanh(z1)) - 5.7 / 2 * (1 + math.tanh(z2))


class KinematicCar:
    wheelbase, mass, wheel_radius = 2.7, 1648.0, 0.3

    def __init__(self, x: float, y: float, yaw: float, v: float) -> None:
        self.x, self.y, self.yaw, self.v = x, y, yaw, v
        self.steer, self.torque = 0.0, 0.0

    def step(self, dt: float) -> None:
        self.x += self.v * math.cos(self.yaw) * dt
        self.y += self.v * math.sin(self.yaw) * dt
        self.yaw += self.v / self.wheelbase * math.tan(self.steer) * dt
        self.v = max(0.0, self.v + self.torque / (self.mass * self.wheel_radius) * dt)


def test_a_contract_only_plant_drives_the_ecu():
    from firmware_sim.ecu import Ecu

    channel = "third-party-rig"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    ecu = Ecu(ecu_bus, "lmpc", {7: PATH_FILE}, lockstep=True)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,), daemon=True)
    thread.start()
    rig = can.Bus(interface="virtual", channel=channel)
    car = KinematicCar(10.0, dlc_y(10.0), 0.0026, 35 / 3.6)
    plant_cnt = planner_cnt = 0
    modes, worst_e_y, commands = [], 0.0, 0
    try:
        # Handshake: HIL_SYNC 0xFFFFFFFF every 100 ms until the ECU answers.
        for _ in range(300):
            rig.send(can.Message(arbitration_id=0x080, data=struct.pack("<II", HANDSHAKE, 0),
                                 is_extended_id=False))
            reply = rig.recv(timeout=0.1)
            if reply is not None and reply.arbitration_id == 0x081 \
                    and struct.unpack("<I", bytes(reply.data[:4]))[0] == HANDSHAKE:
                break
        else:
            pytest.fail("no handshake answer from the ECU in 30 s")
        for tick in range(0, 1500, 5):
            if tick % 10 == 0:
                yaw = (car.yaw + math.pi) % (2 * math.pi) - math.pi
                frames = {
                    0x100: struct.pack("<hhh", sat(car.v / 0.01, 16), 0, sat(car.v / car.wheelbase * math.tan(car.steer) / 1e-4, 16)),
                    0x101: int24(sat(car.x / 1e-3, 24)) + int24(sat(car.y / 1e-3, 24)),
                    0x102: struct.pack("<hhh", sat(yaw / 1e-4, 16), sat(car.steer / 1e-4, 16), sat(car.torque / 0.1, 16)),
                }
                for frame_id, body in frames.items():  # one counter for the three frames
                    rig.send(can.Message(arbitration_id=frame_id, is_extended_id=False,
                                         data=protected(frame_id, plant_cnt, 0, body)))
                plant_cnt = (plant_cnt + 1) % 16
            if tick % 25 == 0:
                body = struct.pack("<HBBH", round(35 / 3.6 / 0.01), 7, 0, 0)
                rig.send(can.Message(arbitration_id=0x110, is_extended_id=False,
                                     data=protected(0x110, planner_cnt, 0b0001, body)))  # ENGAGE
                planner_cnt = (planner_cnt + 1) % 16
            rig.send(can.Message(arbitration_id=0x080, data=struct.pack("<II", tick, 0),
                                 is_extended_id=False))
            while True:
                reply = rig.recv(timeout=10.0)
                assert reply is not None, f"no ACK for TICK={tick}"
                data = bytes(reply.data)
                if reply.arbitration_id == 0x081 and struct.unpack("<I", data[:4])[0] == tick:
                    break
                if reply.arbitration_id != 0x200:
                    continue
                assert data[0] == crc8_sae_j1850_bitwise(b"\x00\x02" + data[1:]), "command CRC"
                mode, valid = (data[1] >> 4) & 0x07, data[1] >> 7
                steer, torque = struct.unpack("<hh", data[2:6])
                modes.append(mode)
                commands += 1
                if valid:
                    car.steer = max(-0.3, min(0.3, steer * 1e-4))
                    car.torque = torque * 0.1
                else:
                    car.torque = 0.0
            car.step(0.005)
            worst_e_y = max(worst_e_y, abs(car.y - dlc_y(car.x)))
    finally:
        stop.set()
        thread.join(timeout=2)
        ecu.close()
        rig.shutdown()
    print(f"{commands} commands, modes {sorted(set(modes))}, car at X = {car.x:.1f} m, "
          f"worst |Y - Y_path(X)| = {worst_e_y:.3f} m")
    assert commands == 60
    assert modes[0] in (1, 2) and all(mode == 2 for mode in modes[1:]), "ACTIVE after one cycle"
    assert car.x > 24.0
    assert worst_e_y < 0.15, "the ECU steers a foreign plant along the path"

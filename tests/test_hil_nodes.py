"""Plant and planner nodes against the CAN contract, checked from raw bytes.

The payloads are read with struct/bit arithmetic and an independent bitwise CRC-8
SAE J1850, not with can_defs, so a shared mistake in the codec cannot hide here.
"""
from __future__ import annotations

import dataclasses
import math
import struct

import can
import pytest

from hil.plant_node import COMMAND_TIMEOUT_MS, PlantFaultError, PlantNode, mu_step_from_faults
from hil.planner_node import PlannerNode
from hil.scenario import load_scenario

from contract_reference import crc8_sae_j1850_bitwise, e2e_ok, signed, unsigned


def steer_cmd_payload(counter: int, mode: int, valid: bool, steer_rad: float,
                      torque_nm: float, corrupt_crc: bool = False) -> bytes:
    """STEER_TORQUE_CMD built by hand from the contract's table."""
    byte1 = (counter & 0x0F) | (mode & 0x07) << 4 | int(valid) << 7
    body = struct.pack("<BhhH", byte1, round(steer_rad / 1e-4), round(torque_nm / 0.1), 0)
    crc = crc8_sae_j1850_bitwise(bytes([0x00, 0x02]) + body)
    return bytes([crc ^ 0xFF if corrupt_crc else crc]) + body


def cmd_message(payload: bytes) -> can.Message:
    return can.Message(arbitration_id=0x200, data=payload, is_extended_id=False)


def test_bitwise_crc_check_value():
    assert crc8_sae_j1850_bitwise(b"123456789") == 0x4B


@pytest.fixture
def smoke():
    return load_scenario("dlc_smoke")


def test_plant_frames_every_10_ms_with_one_counter_per_sample(smoke):
    plant = PlantNode(smoke)
    counters = []
    for tick in range(0, 40, 5):
        frames = plant.frames_due(tick)
        if tick % 10:
            assert frames == [], f"plant frames at t={tick} ms (period 10 ms)"
        else:
            assert [f.arbitration_id for f in frames] == [0x100, 0x101, 0x102]
            assert all(len(f.data) == 8 and not f.is_extended_id for f in frames)
            assert all(e2e_ok(f.arbitration_id, bytes(f.data)) for f in frames)
            tick_counters = {f.data[1] & 0x0F for f in frames}
            assert len(tick_counters) == 1, f"torn sample at t={tick}: {tick_counters}"
            counters.append(tick_counters.pop())
        plant.advance(tick, 0.005)
    print("plant counters", counters)
    assert counters == [0, 1, 2, 3]


def test_plant_signals_match_the_vehicle_within_one_lsb(smoke):
    plant = PlantNode(smoke)
    out = plant.vehicle.outputs()
    dyn, xy, yaw = (bytes(f.data) for f in plant.frames_due(0))
    decoded = {
        "vx": signed(dyn, 16, 16) * 0.01, "vy": signed(dyn, 32, 16) * 0.001,
        "yaw_rate": signed(dyn, 48, 16) * 1e-4,
        "x": signed(xy, 16, 24) * 1e-3, "y": signed(xy, 40, 24) * 1e-3,
        "yaw": signed(yaw, 16, 16) * 1e-4, "steer_angle": signed(yaw, 32, 16) * 1e-4,
        "drive_torque": signed(yaw, 48, 16) * 0.1,
    }
    lsb = {"vx": 0.01, "vy": 0.001, "yaw_rate": 1e-4, "x": 1e-3, "y": 1e-3, "yaw": 1e-4,
           "steer_angle": 1e-4, "drive_torque": 0.1}
    for name, value in decoded.items():
        error = abs(value - getattr(out, name))
        print(f"{name}: sent {value:.6g}, true {getattr(out, name):.6g}, error {error:.2g}")
        assert error <= lsb[name] / 2 + 1e-12
    assert decoded["x"] == pytest.approx(10.0) and decoded["vx"] == pytest.approx(35 / 3.6, abs=0.005)


def test_plant_yaw_is_wrapped_to_minus_pi_pi(smoke):
    scenario = dataclasses.replace(smoke, start=dataclasses.replace(smoke.start, yaw_rad=math.pi))
    plant = PlantNode(scenario)
    yaw_frame = bytes(plant.frames_due(0)[2].data)
    sent = signed(yaw_frame, 16, 16) * 1e-4
    print("yaw pi is sent as", sent)
    assert sent == pytest.approx(-math.pi, abs=1e-4)


def test_plant_applies_only_valid_commands_and_saturates_steering(smoke):
    plant = PlantNode(smoke)
    plant.receive(cmd_message(steer_cmd_payload(0, 2, True, 0.5, 120.0)), 0)
    applied = plant.apply_newest_command(0)
    assert applied.steer_angle == pytest.approx(0.3), "actuator saturates at +-0.3 rad"
    assert applied.drive_torque == pytest.approx(120.0)
    # CMD_VALID = 0: hold the last applied steering, zero torque.
    plant.receive(cmd_message(steer_cmd_payload(1, 1, False, -0.2, 300.0)), 25)
    applied = plant.apply_newest_command(25)
    assert (applied.steer_angle, applied.drive_torque) == (pytest.approx(0.3), 0.0)
    # A bad CRC and a repeated counter are discarded; the older good one stays.
    plant.receive(cmd_message(steer_cmd_payload(2, 2, True, 0.1, 50.0)), 50)
    plant.receive(cmd_message(steer_cmd_payload(3, 2, True, -0.1, 60.0, corrupt_crc=True)), 50)
    plant.receive(cmd_message(steer_cmd_payload(2, 2, True, -0.2, 70.0)), 50)
    applied = plant.apply_newest_command(50)
    print("after CRC error and repeat:", applied, "rejected", plant.commands_rejected)
    assert (applied.steer_angle, applied.drive_torque) == (pytest.approx(0.1), pytest.approx(50.0))
    assert plant.commands_rejected == 2


def test_plant_newest_of_several_commands_wins(smoke):
    plant = PlantNode(smoke)
    plant.receive(cmd_message(steer_cmd_payload(0, 2, True, 0.05, 10.0)), 0)
    plant.receive(cmd_message(steer_cmd_payload(1, 2, True, -0.07, 20.0)), 0)
    applied = plant.apply_newest_command(0)
    assert (applied.steer_angle, applied.drive_torque) == (pytest.approx(-0.07), pytest.approx(20.0))


def test_plant_stops_driving_when_commands_stop(smoke):
    plant = PlantNode(smoke)
    plant.receive(cmd_message(steer_cmd_payload(0, 2, True, 0.02, 200.0)), 0)
    plant.apply_newest_command(0)
    torques = {t: plant.apply_newest_command(t).drive_torque for t in range(5, 160, 5)}
    print("torque after the last command:", {t: torques[t] for t in (95, 100, 105)})
    assert torques[COMMAND_TIMEOUT_MS] == pytest.approx(200.0)
    assert torques[COMMAND_TIMEOUT_MS + 5] == 0.0
    assert plant.applied.steer_angle == pytest.approx(0.02), "steering held"


def test_plant_mu_step_from_scenario_faults(smoke):
    scenario = dataclasses.replace(smoke, faults={"mu_step": {"time_s": 0.01, "mu": 0.4}})
    plant = PlantNode(scenario)
    plant.advance(0, 0.005)
    assert plant.vehicle.mu == pytest.approx(0.85)
    plant.advance(10, 0.005)
    assert plant.vehicle.mu == pytest.approx(0.4)


@pytest.mark.parametrize("faults, fragment", [
    ({"mu_step": 0.5}, "exactly time_s and mu"),
    ({"mu_step": {"time_s": 1.0, "mu": 0.0}}, "faults.mu_step.mu = 0.0"),
    ({"mu_step": {"time_s": -1.0, "mu": 0.5}}, "faults.mu_step.time_s = -1.0"),
    ({"mu_step": {"time_s": float("nan"), "mu": 0.5}}, "finite"),
])
def test_bad_mu_step_is_a_typed_error_naming_the_field(faults, fragment):
    with pytest.raises(PlantFaultError, match=fragment.replace(".", r"\.")):
        mu_step_from_faults(faults, "s.toml")
    assert mu_step_from_faults({"can_drop": {}}) is None, "bus faults are not the plant's"


def test_planner_request_every_25_ms_from_the_speed_profile():
    scenario = load_scenario("dlc_low_mu")
    planner = PlannerNode(scenario, engage=lambda t: t < 0.05)
    sent = {}
    for tick in range(0, 3100, 5):
        frames = planner.frames_due(tick)
        assert len(frames) == (1 if tick % 25 == 0 else 0)
        if frames:
            sent[tick] = bytes(frames[0].data)
    counters = [data[1] & 0x0F for data in sent.values()]
    assert counters[:17] == list(range(16)) + [0]
    assert all(e2e_ok(0x110, data) for data in sent.values())
    engage = {t: unsigned(d, 12, 1) for t, d in sent.items()}
    assert engage[0] == engage[25] == 1 and engage[50] == 0
    speeds = {t: unsigned(d, 16, 16) * 0.01 for t, d in sent.items()}
    print("target speed at 0 / 1.5 / 3.0 s:", speeds[0], speeds[1500], speeds[3000])
    assert speeds[0] == pytest.approx(50 / 3.6, abs=0.005)
    assert speeds[1500] == pytest.approx(52.5 / 3.6, abs=0.005)
    assert speeds[3000] == pytest.approx(55 / 3.6, abs=0.005)
    assert {unsigned(d, 32, 8) for d in sent.values()} == {scenario.path_id}

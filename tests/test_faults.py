"""Fault injection (hil/faults.py), the campaign's judge (studies/fault_campaign.py) and the
``python -m hil faults`` flags: every bus fault does exactly what it says to the frames,
deterministically for a seed; bad specs name the field; the independent command check
catches a bad command; a short lockstep run with the plant silent shows DEGRADED within
the contract's bound and no invalid command."""
from __future__ import annotations

import argparse
import dataclasses
import math

import can
import numpy as np
import pytest

from can_defs.codec import decode, encode
from can_defs.frames import (CtrlMode, FrameId, HilSync, PlannerReq, SteerTorqueCmd, VehDyn,
                             VehPoseXY, VehPoseYaw)
from hil.commands.faults import faults_table, parse_pairs
from studies.fault_campaign import (DEGRADED, FaultCase, check_commands, mode_sequence, run_case)
from hil.faults import FaultInjector, FaultSpec, FaultSpecError, OffsetSteeringVehicle
from hil.scenario import load_scenario


def plant_frames(counter: int, vx: float = 10.0) -> list[can.Message]:
    frames = (VehDyn(vx, 0.1, 0.02), VehPoseXY(5.0, 0.5), VehPoseYaw(0.01, 0.02, 100.0))
    return [can.Message(arbitration_id=int(f.FRAME_ID), data=encode(f, counter),
                        is_extended_id=False) for f in frames]


def planner_frame(counter: int) -> can.Message:
    return can.Message(arbitration_id=int(FrameId.PLANNER_REQ), is_extended_id=False,
                       data=encode(PlannerReq(True, 10.0, 1), counter))


def run_ticks(spec: FaultSpec, n_ticks: int = 40) -> list[tuple[int, can.Message]]:
    """Regular plant (10 ms) and planner (25 ms) traffic through an injector: (tick, frame)."""
    injector = FaultInjector(spec)
    out = []
    for index in range(n_ticks):
        tick = 5 * index
        frames = []
        if tick % 10 == 0:
            frames += plant_frames((tick // 10) % 16)
        if tick % 25 == 0:
            frames.append(planner_frame((tick // 25) % 16))
        out += [(tick, m) for m in injector.outgoing(tick, frames)]
    return out


def spec(**fault) -> FaultSpec:
    return FaultSpec.from_mapping({"seed": 3, "bus": [fault]})


def counters(out, frame_id=FrameId.VEH_DYN):
    return [decode(m.arbitration_id, bytes(m.data)).counter for _, m in out
            if m.arbitration_id == frame_id]


def test_no_fault_passes_everything_unchanged():
    clean = run_ticks(FaultSpec())
    assert len(clean) == 20 * 3 + 8
    assert counters(clean) == [i % 16 for i in range(20)]


def test_silent_window_removes_only_the_sender_inside_it():
    out = run_ticks(spec(kind="silent", sender="plant", start_s=0.05, duration_s=0.03))
    plant_ticks = sorted({t for t, m in out if m.arbitration_id == FrameId.VEH_DYN})
    assert plant_ticks == [t for t in range(0, 200, 10) if not 50 <= t < 80]
    assert len([m for _, m in out if m.arbitration_id == FrameId.PLANNER_REQ]) == 8


def test_delay_holds_frames_by_whole_ticks_unchanged():
    clean = {(t, bytes(m.data)) for t, m in run_ticks(FaultSpec()) if m.arbitration_id == FrameId.VEH_DYN}
    delayed = {(t - 20, bytes(m.data)) for t, m in run_ticks(spec(kind="delay", delay_ms=20))
               if m.arbitration_id == FrameId.VEH_DYN}
    assert delayed == {(t, d) for t, d in clean if t < 180}


def test_duplicate_repeats_the_payload():
    out = run_ticks(spec(kind="duplicate", start_s=0.1))
    ids = counters(out)
    assert ids[:10] == list(range(10)) and ids[10:14] == [10, 10, 11, 11]


def test_bitflip_flips_one_bit_and_breaks_the_crc():
    clean = run_ticks(FaultSpec())
    flipped = run_ticks(spec(kind="bitflip", rate=1.0))
    for (_, a), (_, b) in zip(clean, flipped):
        diff = int.from_bytes(bytes(a.data), "little") ^ int.from_bytes(bytes(b.data), "little")
        if a.arbitration_id == FrameId.PLANNER_REQ:
            assert diff == 0
        else:
            assert bin(diff).count("1") == 1
            assert not decode(b.arbitration_id, bytes(b.data)).crc_ok


def test_wrong_crc_and_frozen_counter():
    wrong = run_ticks(spec(kind="wrong_crc", start_s=0.0, duration_s=0.02))
    verdicts = [decode(m.arbitration_id, bytes(m.data)).crc_ok for t, m in wrong
                if m.arbitration_id == FrameId.VEH_DYN]
    assert verdicts[:2] == [False, False] and all(verdicts[2:])
    frozen = run_ticks(spec(kind="frozen_counter", start_s=0.05))
    assert counters(frozen) == [0, 1, 2, 3, 4] + [5] * 15
    assert all(decode(m.arbitration_id, bytes(m.data)).crc_ok for _, m in frozen)


def test_reorder_sends_an_instant_after_the_next_one():
    out = run_ticks(spec(kind="reorder", rate=1.0, start_s=0.05, duration_s=0.01))
    assert counters(out)[:8] == [0, 1, 2, 3, 4, 6, 5, 7]


def test_babble_floods_and_starves_lower_priority_ids():
    out = run_ticks(spec(kind="babble", babble_id=0x0FF, frames_per_tick=4, start_s=0.05,
                         duration_s=0.05))
    window = [m for t, m in out if 50 <= t < 100]
    assert window and all(m.arbitration_id == 0x0FF for m in window)
    assert len(window) == 10 * 4
    assert any(m.arbitration_id == FrameId.VEH_DYN for t, m in out if t >= 100)


def test_override_saturates_and_keeps_e2e_valid():
    out = run_ticks(spec(kind="override", sender="plant", field="vx", value=1e9))
    for _, m in out:
        decoded = decode(m.arbitration_id, bytes(m.data))
        assert decoded.crc_ok
        if m.arbitration_id == FrameId.VEH_DYN:
            assert decoded.frame.vx == pytest.approx(327.67)
            assert decoded.frame.vy == pytest.approx(0.1)
    assert counters(out) == [i % 16 for i in range(20)]


def test_engage_toggle_alternates():
    out = run_ticks(spec(kind="engage_toggle", sender="planner", period_ms=50), n_ticks=40)
    engage = [decode(m.arbitration_id, bytes(m.data)).frame.engage for _, m in out
              if m.arbitration_id == FrameId.PLANNER_REQ]
    assert engage == [False, False, True, True, False, False, True, True]


def test_sensor_bias_is_added_to_vy_and_yaw_rate_only():
    injector = FaultInjector(FaultSpec.from_mapping({"sensor": {"vy_bias": 0.05, "yaw_rate_bias": 0.01}}))
    out = injector.outgoing(0, plant_frames(0))
    dyn = decode(int(FrameId.VEH_DYN), bytes(out[0].data)).frame
    assert (dyn.vx, dyn.vy, dyn.yaw_rate) == pytest.approx((10.0, 0.15, 0.03))
    assert bytes(out[1].data) == bytes(plant_frames(0)[1].data)


def test_random_faults_are_deterministic_for_a_seed():
    fault = {"kind": "drop", "rate": 0.3, "burst": 2}
    a = [bytes(m.data) for _, m in run_ticks(FaultSpec.from_mapping({"seed": 7, "bus": [fault]}), 200)]
    b = [bytes(m.data) for _, m in run_ticks(FaultSpec.from_mapping({"seed": 7, "bus": [fault]}), 200)]
    c = [bytes(m.data) for _, m in run_ticks(FaultSpec.from_mapping({"seed": 8, "bus": [fault]}), 200)]
    assert a == b and a != c
    assert 0.2 < 1 - len(a) / len(run_ticks(FaultSpec(), 200)) < 0.45


@pytest.mark.parametrize("table, message", [
    ({"bus": [{"kind": "explode"}]}, "faults.bus[0].kind = 'explode'"),
    ({"bus": [{"kind": "drop"}]}, "needs rate"),
    ({"bus": [{"kind": "drop", "rate": 1.5}]}, "faults.bus[0].rate = 1.5"),
    ({"bus": [{"kind": "delay", "delay_ms": 7}]}, "multiple of 5"),
    ({"bus": [{"kind": "override", "field": "speed", "value": 1}]}, "not a field of VehDyn"),
    ({"bus": [{"kind": "silent", "sender": "radar"}]}, "sender = 'radar'"),
    ({"bus": [{"kind": "silent", "rate": 1}]}, "unknown key(s) rate"),
    ({"vehicle": {"mass": 200}}, "faults.vehicle: unknown key(s) mass"),
    ({"sensor": {"vy_noise": -1}}, "noise levels must be >= 0"),
    ({"seed": -1}, "faults.seed"),
    ({"typo": 1}, "unknown key(s) typo"),
])
def test_bad_specs_name_what_is_wrong(table, message):
    with pytest.raises(FaultSpecError) as info:
        FaultSpec.from_mapping(table, "scenario.toml")
    assert message in str(info.value) and "scenario.toml" in str(info.value)


def test_vehicle_faults_change_the_plant():
    scenario = load_scenario("dlc_smoke")
    plain = FaultInjector(FaultSpec()).vehicle(scenario)
    assert plain is None
    heavy = FaultInjector(FaultSpec.from_mapping({"vehicle": {"mass_offset_kg": 200.0,
                                                              "steer_extra_lag_s": 0.1}})).vehicle(scenario)
    nominal = scenario.vehicle_params()
    assert heavy.params.mass == pytest.approx(nominal.mass + 200.0)
    assert heavy.params.steer_time_constant == pytest.approx(nominal.steer_time_constant + 0.1)
    offset = FaultInjector(FaultSpec.from_mapping({"vehicle": {"steer_offset_rad": 0.02}})).vehicle(scenario)
    assert isinstance(offset, OffsetSteeringVehicle)
    from models.vehicle import VehicleCommand

    offset.reset(vx=10.0)
    for _ in range(200):   # 1 s: the actuator settles at command + offset
        out = offset.step(VehicleCommand(drive_torque=0.0, steer_angle=0.01), 0.005)
    assert out.steer_angle == pytest.approx(0.03, abs=1e-3)


def test_command_check_catches_each_kind_of_bad_command():
    def frame(mode, valid, steer, torque, corrupt=False):
        data = bytearray(encode(SteerTorqueCmd(mode, valid, steer, torque), 0))
        if corrupt:
            data[0] ^= 1
        return (0, int(FrameId.STEER_TORQUE_CMD), bytes(data))

    good = [frame(CtrlMode.ACTIVE, True, 0.3, 3000.0), frame(CtrlMode.SAFE_STOP, True, 0.0, -1500.0),
            frame(CtrlMode.STANDBY, False, 2.0, 3200.0)]   # CMD_VALID = 0: not applied
    assert check_commands(good)[:2] == (0, 2)
    bad = [frame(CtrlMode.ACTIVE, True, 0.31, 0.0), frame(CtrlMode.ACTIVE, True, 0.0, 3100.0),
           frame(CtrlMode.STANDBY, True, 0.0, 0.0), frame(CtrlMode.SAFE_STOP, True, 0.0, 10.0),
           frame(CtrlMode.ACTIVE, True, 0.0, 0.0, corrupt=True)]
    invalid, checked, reasons = check_commands(bad)
    assert (invalid, checked) == (5, 5), reasons


def test_mode_sequence_starts_at_the_first_active():
    times = np.arange(6) * 0.025
    modes = np.array([0, 1, 2, 3, 3, 2])
    assert mode_sequence(times, modes) == "ACTIVE, DEGRADED@0.075, ACTIVE@0.125"


def test_cli_flags_build_the_faults_table():
    args = argparse.Namespace(bus=["kind=drop,rate=0.1,burst=3,ids=0x100/0x101,start_s=3"],
                              mass_offset=200.0, steer_offset=None, steer_lag=0.1,
                              sensor="vy_bias=0.05", mu_step="3.0:0.5", seed=4)
    table = faults_table(args, {"bus": [{"kind": "silent"}]})
    assert table["bus"][1] == {"kind": "drop", "rate": 0.1, "burst": 3, "ids": [0x100, 0x101],
                               "start_s": 3}
    assert table["vehicle"] == {"mass_offset_kg": 200.0, "steer_extra_lag_s": 0.1}
    assert table["mu_step"] == {"time_s": 3.0, "mu": 0.5} and table["seed"] == 4
    parsed = FaultSpec.from_mapping(table)
    assert len(parsed.bus) == 2 and parsed.sensor.vy_bias == 0.05
    with pytest.raises(FaultSpecError, match="'rate' is not key=value"):
        parse_pairs("kind=drop,rate", "--bus")


def test_short_lockstep_run_with_the_plant_silent_degrades_in_time():
    """Plant silent 60 ms at 0.5 s of the smoke scenario (LMPC, 1 s of virtual time):
    DEGRADED within the contract's bound, back to ACTIVE, no invalid command, no crash."""
    case = FaultCase("silent", "bus", {"bus": [{"kind": "silent", "start_s": 0.5,
                                                "duration_s": 0.06}]}, ("lmpc",), (DEGRADED,))
    verdict = run_case(case, "lmpc", "dlc_smoke", duration_s=1.0)
    print(f"\n{verdict.mode_sequence}; detect {verdict.detect_ms} ms; {verdict.expects}; "
          f"max|e_Y| {verdict.max_abs_ey_m:.3f} m; invalid {verdict.invalid_commands} of "
          f"{verdict.commands_checked}")
    assert verdict.crashes == 0 and verdict.invalid_commands == 0
    assert verdict.commands_checked > 30
    assert verdict.expects[0]["met"] and verdict.expects[0]["at_ms"] == 25
    assert verdict.mode_sequence == "ACTIVE, DEGRADED@0.525, ACTIVE@0.575"
    assert verdict.outcome == "tracked"


def test_reorder_at_a_partial_rate_only_permutes_instants():
    out = run_ticks(spec(kind="reorder", rate=0.4), n_ticks=200)
    seen = counters(out)
    assert len(seen) == 100 and seen != [i % 16 for i in range(100)]
    assert sorted(seen) == sorted(i % 16 for i in range(100))


def test_cli_refuses_a_bad_fault_with_a_clear_error(capsys):
    from hil.__main__ import main

    assert main(["faults", "--scenario", "dlc_smoke", "--bus", "kind=explode,start_s=1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "faults.bus[0].kind = 'explode'" in err
    assert "dlc_smoke.toml + flags" in err


def test_cli_one_run_prints_the_verdict(capsys):
    import json

    from hil.__main__ import main

    rc = main(["faults", "--scenario", "dlc_smoke", "--controller", "lmpc", "--duration", "0.5",
               "--bus", "kind=silent,sender=plant,start_s=0.2,duration_s=0.06", "--seed", "2"])
    verdict = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert verdict["mode_sequence"] == "ACTIVE, DEGRADED@0.225, ACTIVE@0.275"
    assert verdict["description"] == "silent plant, 0.2-0.26 s"
    assert (verdict["crashes"], verdict["invalid_commands"]) == (0, 0)

"""Fault injection (hil/faults.py, hil/fault_*.py), the campaign's judge
(studies/fault_verdicts.py) and the ``python -m hil faults`` flags: every bus fault does
exactly what it says to the frames, deterministically for a seed; bad specs name the
field; the independent command check catches a bad command; a short lockstep run with the
plant silent shows DEGRADED within the contract's bound and no invalid command."""
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
from hil.fault_cases.catalogue import DEGRADED, FaultCase
from hil.fault_cases.runs import run_case
from hil.fault_cases.verdicts import check_commands, mode_sequence
from hil.fault_injector import FaultInjector
from hil.fault_vehicle import OffsetSteeringVehicle
from hil.faults import FaultSpec, FaultSpecError
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
    ({"vehicle": {"cornering_stiffness_rear_scale": 0.0}}, "faults.vehicle.cornering_stiffness_rear_scale = 0.0"),
    ({"vehicle": {"cornering_stiffness_rear_scale": 2.5}}, "must be in (0, 2]"),
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
    assert heavy.params.cornering_stiffness_rear_scale == 1.0
    # The rear tyres alone (every other fault at its default) still make a changed plant.
    worn = FaultInjector(FaultSpec.from_mapping({"vehicle": {"cornering_stiffness_rear_scale": 0.8}})).vehicle(scenario)
    assert worn.params.cornering_stiffness_rear_scale == 0.8 and worn.params.mass == nominal.mass
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
                              mass_offset=200.0, steer_offset=None, steer_lag=0.1, rear_stiffness=0.8,
                              sensor="vy_bias=0.05", mu_step="3.0:0.5", seed=4)
    table = faults_table(args, {"bus": [{"kind": "silent"}]})
    assert table["bus"][1] == {"kind": "drop", "rate": 0.1, "burst": 3, "ids": [0x100, 0x101],
                               "start_s": 3}
    assert table["vehicle"] == {"mass_offset_kg": 200.0, "steer_extra_lag_s": 0.1,
                                "cornering_stiffness_rear_scale": 0.8}
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


# --- contract revision 2: look-alikes, replays, implausible values, jumps, a lost bus -------

from can_defs.frames import HANDSHAKE_TICK  # noqa: E402
from hil.fault_buses import BusDownError, LosableBus, TimeShiftingBus  # noqa: E402
from hil.fault_cases import catalogue as fault_cases, verdicts as fault_verdicts  # noqa: E402
from studies import fault_report  # noqa: E402

RX_PLANT_AND_PLANNER = [0x100, 0x101, 0x102, 0x110]


def test_lookalikes_follow_each_frame_in_another_kind_with_the_next_counter():
    out = run_ticks(spec(kind="lookalike", ids=RX_PLANT_AND_PLANNER, frame_kind="fd",
                         sync_tick=HANDSHAKE_TICK, start_s=0.05, duration_s=0.05))
    before = [m for t, m in out if t < 50]
    window = [(t, m) for t, m in out if 50 <= t < 100]
    assert not any(m.is_fd for m in before)
    fd = [m for _, m in window if m.is_fd]
    classic = [m for _, m in window if not m.is_fd]
    assert len(fd) == len(classic) + 10       # one copy per frame + one HIL_SYNC per tick
    syncs = [m for m in fd if m.arbitration_id == FrameId.HIL_SYNC]
    assert len(syncs) == 10 and all(decode(m.arbitration_id, bytes(m.data)).frame.tick
                                    == HANDSHAKE_TICK for m in syncs)
    for real, copy in zip(classic, [m for m in fd if m.arbitration_id != FrameId.HIL_SYNC]):
        assert copy.arbitration_id == real.arbitration_id and not copy.is_extended_id
        real_decoded, copy_decoded = (decode(m.arbitration_id, bytes(m.data)) for m in (real, copy))
        assert copy_decoded.crc_ok and copy_decoded.counter == (real_decoded.counter + 1) % 16
        assert copy_decoded.frame == real_decoded.frame


@pytest.mark.parametrize("frame_kind, flag", [("extended", "is_extended_id"),
                                              ("remote", "is_remote_frame"),
                                              ("error", "is_error_frame")])
def test_lookalikes_of_each_kind_carry_its_flag(frame_kind, flag):
    out = run_ticks(spec(kind="lookalike", sender="plant", frame_kind=frame_kind))
    odd = [m for _, m in out if getattr(m, flag)]
    assert len(odd) == 60 and all(m.arbitration_id in (0x100, 0x101, 0x102) for m in odd)
    assert all((len(m.data) == 0) == (frame_kind == "remote") for m in odd)


def test_replay_resends_the_frames_of_age_ms_earlier_unchanged():
    clean = run_ticks(FaultSpec())
    by_tick = {}
    for t, m in clean:
        if m.arbitration_id in (0x100, 0x101, 0x102):
            by_tick.setdefault(t, []).append(bytes(m.data))
    added = run_ticks(spec(kind="replay", age_ms=50, start_s=0.1))
    for tick in range(100, 200, 10):
        sent = [bytes(m.data) for t, m in added if t == tick and m.arbitration_id != 0x110]
        assert sent == by_tick[tick] + by_tick[tick - 50]     # real ones, then the replay
    replaced = run_ticks(spec(kind="replay", age_ms=160, start_s=0.16, replace=True))
    # 16 instants earlier: the counters read exactly as the real sender's would
    assert counters(replaced) == [i % 16 for i in range(20)]
    assert [bytes(m.data) for t, m in replaced if t == 170 and m.arbitration_id != 0x110] \
        == by_tick[10]


@pytest.mark.parametrize("fault, message", [
    ({"kind": "lookalike", "frame_kind": "xl"}, "frame_kind = 'xl'"),
    ({"kind": "lookalike", "frame_kind": "remote", "sync_tick": 5}, "only fd and extended"),
    ({"kind": "lookalike"}, "needs frame_kind"),
    ({"kind": "replay", "age_ms": 7}, "age_ms = 7: must be a multiple of 5"),
    ({"kind": "replay", "age_ms": 50, "replace": 1}, "replace = 1"),
])
def test_bad_rev2_specs_name_what_is_wrong(fault, message):
    with pytest.raises(FaultSpecError, match=message.replace("(", r"\(")):
        FaultSpec.from_mapping({"bus": [fault]}, "scenario.toml")


def test_time_shifting_bus_shifts_sync_out_and_ack_back():
    channel = f"faults-shift-{id(object())}"
    master, ecu = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    shifted = TimeShiftingBus(master, from_tick_ms=100, ahead_ms=10_000)
    try:
        for tick in (HANDSHAKE_TICK, 95, 100):
            shifted.send(can.Message(arbitration_id=int(FrameId.HIL_SYNC), is_extended_id=False,
                                     data=encode(HilSync(tick))))
        seen = [decode(m.arbitration_id, bytes(m.data)).frame.tick
                for m in iter(lambda: ecu.recv(0.1), None)]
        assert seen == [HANDSHAKE_TICK, 95, 10_100]
        for tick in (95, 10_100):
            data = encode(HilSync(tick))   # an ACK has the same layout
            ecu.send(can.Message(arbitration_id=int(FrameId.HIL_SYNC_ACK), data=data,
                                 is_extended_id=False))
        acks = [int.from_bytes(bytes(shifted.recv(0.1).data[:4]), "little") for _ in range(2)]
        assert acks == [95, 100] and shifted.record.actions == 1
    finally:
        shifted.shutdown()
        ecu.shutdown()


def test_losable_bus_fails_every_call_once_lost_and_counts_them():
    channel = f"faults-lose-{id(object())}"
    bus = LosableBus(can.Bus(interface="virtual", channel=channel))
    try:
        assert bus.recv(0.0) is None
        bus.lose()
        for call in (lambda: bus.recv(0.0), lambda: bus.send(planner_frame(0))):
            with pytest.raises(BusDownError):
                call()
        assert bus.calls_while_lost == 2
    finally:
        bus.shutdown()


def short(name: str, start_s: float = 0.5, **ecu_fault) -> FaultCase:
    """A case of the campaign as defined there, moved to ``start_s`` (short smoke runs)."""
    case = next(c for c in fault_cases.all_cases() if c.name == name)
    table = {**case.table, "bus": [{**b, "start_s": start_s} for b in case.table.get("bus", [])]}
    fault = None if case.ecu_fault is None else {**case.ecu_fault, "start_s": start_s, **ecu_fault}
    return dataclasses.replace(case, table=table, ecu_fault=fault, controllers=("lmpc",))


def smoke(case: FaultCase, duration_s: float = 1.0) -> fault_verdicts.Verdict:
    verdict = run_case(case, "lmpc", "dlc_smoke", duration_s=duration_s)
    print(f"\n{case.name}: {verdict.mode_sequence}; "
          f"{[(e['expect'], e.get('shown', e['at_ms']), e['met']) for e in verdict.expects]}")
    assert verdict.crashes == 0 and verdict.invalid_commands == 0, verdict.crash_reason
    return verdict


def missed(verdict: fault_verdicts.Verdict) -> list[str]:
    return [e["expect"] for e in verdict.expects if not e["met"]]


def test_implausible_vx_degrades_and_fails_the_case_without_the_plausibility_check(monkeypatch):
    """VX 327 m/s with a valid CRC: DEGRADED and FAULTS bit 0 (rev. 2). The same case fails
    against an ECU that takes the value as it is (the rev. 1 behaviour)."""
    case = short("VX 327 m/s")
    verdict = smoke(case)
    assert verdict.passed() and verdict.mode_sequence.startswith("ACTIVE, DEGRADED@0.525")
    monkeypatch.setattr("firmware_sim.rx.implausibility", lambda *args, **kwargs: None)
    broken = smoke(case)
    assert not broken.passed() and missed(broken) == ["DEGRADED <= 35 ms", "bit 0 <= 25 ms"]


def test_fd_lookalikes_are_ignored_and_the_case_fails_if_they_were_taken(monkeypatch):
    """CAN FD copies of the plant/planner frames and an FD handshake: no reaction. Taken for
    contract frames, the handshake resets the ECU and the case fails."""
    case = short("CAN FD look-alikes")
    verdict = smoke(case, duration_s=1.6)
    assert verdict.passed() and verdict.mode_sequence == "ACTIVE"
    monkeypatch.setattr("firmware_sim.ecu.is_contract_data_frame", lambda message: True)
    broken = smoke(case, duration_s=1.6)
    assert missed(broken) == ["no reaction for 1000 ms"]


def test_stale_replay_is_an_e2e_error_and_tracking_goes_on():
    verdict = smoke(short("stale replay"), duration_s=1.6)
    assert verdict.passed() and verdict.frames_hit > 0


def test_replay_with_counters_as_next_shows_only_at_its_ends():
    verdict = smoke(short("replay, CNT as next"), duration_s=2.0)
    assert verdict.expects_met
    # in between, the ECU drove on the replayed samples (what no CRC or counter can catch)
    assert "ACTIVE@0.550" in verdict.mode_sequence and "SAFE_STOP@1.600" in verdict.mode_sequence


def test_time_jump_is_adopted_and_fails_the_case_without_the_jump_rule(monkeypatch):
    """HIL_SYNC 10 s ahead: STANDBY with bits 1 and 3 at the jump TICK, one task there,
    re-engaged, the run goes on. Without the rule the case fails."""
    case = short("virtual time jump")
    verdict = smoke(case)
    assert verdict.passed() and verdict.mode_sequence == "ACTIVE, STANDBY@0.500, ACTIVE@0.525"
    monkeypatch.setattr("firmware_sim.ecu.Ecu._on_time_jump", lambda self, tick, skipped: None)
    broken = smoke(case)
    assert "STANDBY <= 0 ms" in missed(broken)


def test_lost_bus_is_noticed_without_spinning_and_the_run_resumes():
    verdict = smoke(short("lost bus", outage_s=1.2))
    assert verdict.passed() and verdict.mode_sequence == "ACTIVE"


@pytest.mark.slow
def test_lost_bus_case_fails_against_an_ecu_that_spins(monkeypatch):
    """The lost-bus case can fail: an ECU that loops without waiting while its bus is lost
    (defect 8) misses the CPU and reopening rules, and the run stalls (a crash)."""
    monkeypatch.setattr("firmware_sim.ecu.Ecu._while_bus_lost", lambda self, stop: None)
    case = short("lost bus", outage_s=1.2)
    verdict = run_case(case, "lmpc", "dlc_smoke", duration_s=1.0)
    print(verdict.expects, verdict.crash_reason)
    assert {"ECU thread CPU < 20 % while lost", "reopen tried every 1 s"} <= set(missed(verdict))
    assert not verdict.passed()


def test_campaign_checks_its_output_folder_before_running(tmp_path, capfd):
    from hil.__main__ import main

    capsys = capfd  # the campaign is the study's command, a process: its output at the fd
    assert main(["faults", "--campaign", "--out", str(tmp_path / "no" / "such")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --out ") and "does not exist" in err and "Traceback" not in err
    (tmp_path / "faults.json").write_text("[]")
    assert main(["faults", "--campaign", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "holds another run's outputs (faults.json)" in err and "--replace" in err
    assert main(["faults", "--campaign", "--out", str(tmp_path), "--only", "nonsense"]) == 1
    assert "unknown case(s) ['nonsense']" in capsys.readouterr().err
    fault_report.check_paths(tmp_path, replace=True)       # told to replace: accepted
    assert not (tmp_path / "no").exists()                   # nothing created on refusal


def test_vehicle_figure_has_a_title_units_and_a_legend_per_line(tmp_path):
    verdicts = [fault_verdicts.Verdict("mass +200 kg", "vehicle", c, "", max_abs_ey_m=0.1,
                                       time_s=[0.0, 0.025], e_y=[0.0, 0.01])
                for c in ("eso-dkmpc", "dkmpc")]
    import matplotlib.pyplot as plt

    created = []
    original = plt.subplots
    def spy(*args, **kwargs):
        created.append(original(*args, **kwargs))
        return created[-1]
    plt.subplots = spy
    try:
        fault_report.figure(verdicts, tmp_path / "f.png")
    finally:
        plt.subplots = original
    fig, axes = created[0]
    assert "dlc_high_mu" in fig._suptitle.get_text() and "e_Y" in fig._suptitle.get_text()
    ax = np.atleast_1d(axes)[0]
    assert ax.get_ylabel() == "e_Y (m)" and np.atleast_1d(axes)[-1].get_xlabel() == "time (s)"
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert len(labels) == len(ax.get_lines()) == 3
    assert (tmp_path / "f.png").stat().st_size > 0


# --- the campaign on the executors (issue 16) ----------------------------------------------

def test_campaign_runs_go_to_this_process_unless_workers_or_an_address_is_given():
    from studies.fault_campaign import executor_options

    def options(**given):
        return executor_options(argparse.Namespace(**{"workers": None, "address": None, "serial": False, **given}))

    assert options() == {"serial": True}
    assert options(workers=2) == {"address": None, "workers": 2}
    assert options(address="127.0.0.1:6379") == {"address": "127.0.0.1:6379", "workers": None}
    with pytest.raises(Exception, match="exclude each other"):
        options(serial=True, address="auto")


@pytest.mark.slow
def test_campaign_on_a_local_ray_gives_the_verdicts_of_a_serial_one():
    pytest.importorskip("ray")
    from hil.fault_cases.catalogue import all_cases
    from studies.fault_runs import run_campaign

    cases = [c for c in all_cases() if c.name in ("drop 5 %", "mass +200 kg")]
    serial = run_campaign(cases, duration_s=2.0)
    parallel = run_campaign(cases, duration_s=2.0, executor_options={"workers": 2})
    assert [(v.case, v.controller) for v in parallel] == [(v.case, v.controller) for v in serial]
    for one, two in zip(serial, parallel):
        assert (one.mode_sequence, one.outcome, one.commands_checked, one.e_y) == \
            (two.mode_sequence, two.outcome, two.commands_checked, two.e_y)

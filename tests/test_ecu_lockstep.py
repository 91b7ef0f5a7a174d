"""The ECU in lockstep over a python-can virtual bus: handshake, task ticks, ACK order,
timeouts, modes, torn samples, E2E errors, unknown paths, guard and determinism.

The ECU runs with a scripted controller (hil.ecu_harness), so these tests check the
node, not a control law. Each test drives time tick by tick through HIL_SYNC.
"""
from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import can
import pytest
from can_defs.codec import decode, encode
from can_defs.frames import (HANDSHAKE_TICK, CtrlDiag, CtrlMode, FrameId, HilSyncAck, QpStatus,
                             SteerTorqueCmd, VehDyn)

from controller.base import Command
from firmware_sim.ecu import Ecu
from hil.ecu_harness import PeerNodes, ScriptedController, commands, decode_messages, diags, pump

PATHS = {1: Path("one.csv"), 2: Path("two.csv")}


def load_path(path: Path) -> str:
    """Stand-in for ReferencePath.from_csv: the file name is the 'path'."""
    return f"path:{path.name}"


@pytest.fixture
def buses():
    channel = f"ecu-lockstep-{uuid.uuid4()}"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    peer_bus = can.Bus(interface="virtual", channel=channel)
    yield ecu_bus, peer_bus
    ecu_bus.shutdown()
    peer_bus.shutdown()


PlantFn = Callable[[int], dict | None]
PlannerFn = Callable[[int], dict | None]


def moving_plant(t: int) -> dict:
    """Plant state at virtual time t (ms): 10 m/s along x, y growing so samples differ."""
    return {"vx": 10.0, "x": 0.01 * t, "y": 0.001 * t}


def engaged(t: int) -> dict:
    return {"engage": True, "target_speed": 10.0, "path_id": 1}


class Rig:
    """ECU + peers; `tick` plays one lockstep tick as the contract's master does."""

    def __init__(self, ecu_bus: can.BusABC, peer_bus: can.BusABC,
                 controller: ScriptedController | None = None, **ecu_kwargs) -> None:
        self.controller = controller or ScriptedController()
        self.ecu_bus = ecu_bus
        self.ecu = Ecu(ecu_bus, "scripted", PATHS, lockstep=True,
                       controller_factory=lambda name: self.controller, path_loader=load_path,
                       **ecu_kwargs)
        self.peers = PeerNodes(peer_bus)
        self.log: dict[int, list[can.Message]] = {}

    def handshake(self) -> list[can.Message]:
        self.peers.send_handshake()
        pump(self.ecu, self.ecu_bus)
        return self.peers.received()

    def tick(self, t: int, plant: PlantFn | None = moving_plant,
             planner: PlannerFn | None = engaged) -> list[can.Message]:
        """(1) frames due at t, (2) HIL_SYNC t; returns what the ECU sent for it."""
        if plant is not None and t % 10 == 0 and (values := plant(t)) is not None:
            self.peers.send_plant(**values)
        if planner is not None and t % 25 == 0 and (request := planner(t)) is not None:
            self.peers.send_planner(**request)
        self.peers.send_sync(t)
        pump(self.ecu, self.ecu_bus)
        sent = self.peers.received()
        self.log[t] = sent
        return sent

    def run(self, start: int, stop: int, **kwargs) -> list[can.Message]:
        sent: list[can.Message] = []
        for t in range(start, stop + 1, 5):
            sent += self.tick(t, **kwargs)
        return sent

    def command_at(self, t: int) -> SteerTorqueCmd:
        (command,) = commands(self.log[t])
        return command

    def diag_at(self, t: int) -> CtrlDiag:
        (diag,) = diags(self.log[t])
        return diag


def ack_ticks(messages: list[can.Message]) -> list[int]:
    return [frame.tick for frame in decode_messages(messages) if isinstance(frame, HilSyncAck)]


# ------------------------------------------------------------------ handshake and ticks
def test_handshake_not_acked_before_ready_then_acked_once_ready(buses):
    ecu_bus, peer_bus = buses
    peers = PeerNodes(peer_bus)
    release_loading = threading.Event()

    def slow_loader(path: Path) -> str:
        release_loading.wait(5.0)
        return load_path(path)

    stop = threading.Event()
    ecus: list[Ecu] = []

    def ecu_thread() -> None:
        ecu = Ecu(ecu_bus, "scripted", PATHS, lockstep=True,
                  controller_factory=lambda name: ScriptedController(), path_loader=slow_loader)
        ecus.append(ecu)
        ecu.run(stop)

    thread = threading.Thread(target=ecu_thread)
    thread.start()
    try:
        peers.send_handshake()
        time.sleep(0.3)  # still loading paths: nothing may answer
        before_ready = peers.received()
        release_loading.set()
        acked = []
        deadline = time.monotonic() + 5.0
        while not acked and time.monotonic() < deadline:
            message = peer_bus.recv(0.1)
            if message is not None:
                acked.append(message)
    finally:
        release_loading.set()
        stop.set()
        thread.join(5.0)
    print("frames before ready:", len(before_ready), "after:", decode_messages(acked))
    assert before_ready == []
    assert ack_ticks(acked) == [HANDSHAKE_TICK]
    assert not thread.is_alive()


def test_ticks_without_handshake_are_not_acked(buses):
    rig = Rig(*buses)
    sent = rig.tick(0)
    print("sent before handshake:", decode_messages(sent))
    assert sent == []
    assert ack_ticks(rig.handshake()) == [HANDSHAKE_TICK]


def test_control_task_runs_at_0_25_50_and_acks_follow_the_commands(buses):
    rig = Rig(*buses)
    rig.handshake()
    sent = rig.run(0, 50)
    frames = decode_messages(sent)
    n_commands = sum(isinstance(f, SteerTorqueCmd) for f in frames)
    print("frame sequence:", [type(f).__name__ for f in frames])
    assert n_commands == 3
    assert ack_ticks(sent) == list(range(0, 55, 5))
    for t in range(0, 55, 5):
        kinds = [type(f) for f in decode_messages(rig.log[t])]
        if t % 25 == 0:   # command, diagnosis, then the ACK
            assert kinds == [SteerTorqueCmd, CtrlDiag, HilSyncAck], (t, kinds)
        else:
            assert kinds == [HilSyncAck], (t, kinds)


def test_repeated_tick_is_acked_again_without_running(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 25)
    steps = len(rig.controller.samples)
    rig.peers.send_sync(25)
    pump(rig.ecu, rig.ecu_bus)
    again = rig.peers.received()
    print("answer to repeated TICK 25:", decode_messages(again))
    assert ack_ticks(again) == [25] and len(again) == 1
    assert len(rig.controller.samples) == steps


def test_skipped_ticks_run_every_due_instant(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.tick(0)
    sent = rig.tick(60)  # master jumped 5 -> 60: instants 25 and 50 are due
    print("after jump to 60:", [type(f).__name__ for f in decode_messages(sent)])
    assert len(commands(sent)) == 2 and ack_ticks(sent) == [60]


def test_handshake_again_restarts_before_tick_0_with_fresh_counters(buses):
    rig = Rig(*buses)
    rig.handshake()
    first = rig.run(0, 50)
    rig.handshake()
    rig.peers.plant_counter = 0
    second = rig.run(0, 50)
    first_cmds = [bytes(m.data) for m in first if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    second_cmds = [bytes(m.data) for m in second if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    assert first_cmds == second_cmds and len(first_cmds) == 3


# ------------------------------------------------------------------ modes
def test_init_standby_active_and_controller_reset_on_engage(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    modes = [rig.command_at(t).ctrl_mode for t in (0, 25, 50)]
    valid = [rig.command_at(t).cmd_valid for t in (0, 25, 50)]
    print("modes:", [m.name for m in modes], "valid:", valid)
    assert modes == [CtrlMode.STANDBY, CtrlMode.ACTIVE, CtrlMode.ACTIVE]
    assert valid == [False, True, True]
    assert rig.controller.resets == 1 and rig.controller.paths == ["path:one.csv"]
    assert rig.diag_at(25).faults & 0b1000 and not rig.diag_at(50).faults & 0b1000
    # the command is the controller's: steer = -0.01 * y of the newest sample (y at 50 ms)
    assert rig.command_at(50).steer_angle_cmd == pytest.approx(-0.01 * 0.05, abs=1e-4)
    assert rig.command_at(50).drive_torque_cmd == pytest.approx(100.0)
    assert rig.diag_at(50).qp_status is QpStatus.SOLVED and rig.diag_at(50).qp_iter == 7
    assert rig.diag_at(0).qp_status is QpStatus.NOT_RUN


def test_stale_sample_degrades_at_over_20_ms_and_safe_stops_past_100_ms(buses):
    rig = Rig(*buses)
    rig.handshake()
    last_plant = 50
    plant = lambda t: moving_plant(t) if t <= last_plant else None
    rig.run(0, 250, plant=plant)
    table = {t: (rig.command_at(t).ctrl_mode, t - last_plant) for t in range(0, 255, 25)}
    print("t: (mode, sample age ms)", {t: (m.name, a) for t, (m, a) in table.items()})
    assert table[50][0] is CtrlMode.ACTIVE                   # age 0
    assert table[75][0] is CtrlMode.DEGRADED                 # age 25 > 20
    assert table[150][0] is CtrlMode.DEGRADED                # age 100: not yet past 100
    assert table[175][0] is CtrlMode.SAFE_STOP               # age 125 > 100
    assert all(rig.command_at(t).cmd_valid for t in range(25, 255, 25))
    assert rig.diag_at(75).faults & 0b0001 and not rig.diag_at(50).faults & 0b0001
    # DEGRADED predicts forward from the last good sample: x advanced by vx * age
    # (the controller is not called in SAFE_STOP: its last sample is the one of t = 150)
    assert len(rig.controller.samples) == 6                      # 25, 50, 75, 100, 125, 150
    degraded_sample = rig.controller.samples[-1]
    print("predicted x at t=150:", degraded_sample.x)
    assert degraded_sample.x == pytest.approx(0.5 + 10.0 * 0.100, abs=1e-6)
    # SAFE_STOP: braking, steering towards straight at <= 0.2 rad/s * 25 ms per cycle
    stops = [rig.command_at(t) for t in range(175, 255, 25)]
    assert all(c.drive_torque_cmd == pytest.approx(-1500.0) for c in stops)
    steers = [rig.command_at(150).steer_angle_cmd] + [c.steer_angle_cmd for c in stops]
    assert all(abs(b) <= abs(a) + 1e-9 and abs(a - b) <= 0.005 + 1e-4 for a, b in zip(steers, steers[1:]))


def test_sample_of_exactly_20_ms_is_still_fresh(buses):
    rig = Rig(*buses)
    rig.handshake()
    plant = lambda t: moving_plant(t) if t <= 30 else None
    rig.run(0, 75, plant=plant)
    print("mode at 50 (age 20):", rig.command_at(50).ctrl_mode.name,
          "at 75 (age 45):", rig.command_at(75).ctrl_mode.name)
    assert rig.command_at(50).ctrl_mode is CtrlMode.ACTIVE
    assert rig.command_at(75).ctrl_mode is CtrlMode.DEGRADED


def test_safe_stop_is_left_only_through_standby_at_standstill_after_engage_0(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    rig.run(55, 175, plant=None)                                 # plant silent -> SAFE_STOP
    assert rig.command_at(175).ctrl_mode is CtrlMode.SAFE_STOP
    rig.run(180, 250)                                            # fresh again, still moving
    assert rig.command_at(250).ctrl_mode is CtrlMode.SAFE_STOP
    standstill = lambda t: {"vx": 0.0, "x": 3.0}
    rig.run(255, 300, plant=standstill)                          # stands, still ENGAGE = 1
    assert rig.command_at(300).ctrl_mode is CtrlMode.SAFE_STOP
    assert rig.command_at(300).drive_torque_cmd == 0.0           # no torque at rest
    disengaged = lambda t: {"engage": False, "target_speed": 0.0, "path_id": 1}
    rig.run(305, 325, plant=standstill, planner=disengaged)
    assert rig.command_at(325).ctrl_mode is CtrlMode.STANDBY
    assert not rig.command_at(325).cmd_valid
    resets = rig.controller.resets
    rig.run(330, 375, plant=standstill)                          # ENGAGE = 1 again
    modes = [rig.command_at(t).ctrl_mode.name for t in range(175, 380, 25)]
    print("modes 175..375:", modes)
    assert rig.command_at(350).ctrl_mode is CtrlMode.ACTIVE
    assert rig.controller.resets == resets + 1


def test_after_safe_stop_a_planner_timeout_needs_engage_0_before_active(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    rig.run(55, 175, plant=None)
    assert rig.command_at(175).ctrl_mode is CtrlMode.SAFE_STOP
    standstill = lambda t: {"vx": 0.0}
    rig.run(180, 325, plant=standstill, planner=None)            # planner silent > 100 ms
    assert rig.command_at(325).ctrl_mode is CtrlMode.STANDBY
    rig.run(330, 400, plant=standstill)                          # ENGAGE = 1 without a 0
    print("mode at 400 with ENGAGE=1 but never 0:", rig.command_at(400).ctrl_mode.name)
    assert rig.command_at(400).ctrl_mode is CtrlMode.STANDBY
    rig.run(405, 425, plant=standstill, planner=lambda t: {"engage": False, "path_id": 1})
    rig.run(430, 475, plant=standstill)
    assert rig.command_at(475).ctrl_mode is CtrlMode.ACTIVE


def test_planner_missing_over_100_ms_returns_to_standby(buses):
    rig = Rig(*buses)
    rig.handshake()
    planner = lambda t: engaged(t) if t <= 50 else None
    rig.run(0, 175, planner=planner)
    modes = {t: rig.command_at(t).ctrl_mode.name for t in range(0, 180, 25)}
    print("modes with the planner silent after 50 ms:", modes)
    assert rig.command_at(150).ctrl_mode is CtrlMode.ACTIVE      # 100 ms old: still on time
    assert rig.command_at(175).ctrl_mode is CtrlMode.STANDBY     # 125 ms old
    assert not rig.command_at(175).cmd_valid
    assert rig.diag_at(175).faults & 0b0001


def test_unknown_path_id_is_an_input_fault_to_standby_never_a_crash(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    rig.run(55, 100, planner=lambda t: {"engage": True, "path_id": 9})
    assert rig.command_at(75).ctrl_mode is CtrlMode.STANDBY
    assert not rig.command_at(75).cmd_valid
    assert rig.diag_at(75).faults & 0b0001
    rig.run(105, 150, planner=lambda t: {"engage": True, "path_id": 2})
    print("paths given to the controller:", rig.controller.paths)
    assert rig.command_at(125).ctrl_mode is CtrlMode.ACTIVE
    assert rig.controller.paths[-1] == "path:two.csv"


def test_path_change_while_active_resets_and_sets_the_new_path(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    rig.run(55, 75, planner=lambda t: {"engage": True, "path_id": 2})
    assert rig.command_at(75).ctrl_mode is CtrlMode.ACTIVE
    assert rig.controller.paths == ["path:one.csv", "path:two.csv"]
    assert rig.controller.resets == 2
    assert rig.diag_at(75).faults & 0b1000


def test_torn_sample_is_never_used(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 40)
    # at 50 the plant's set is torn (VEH_POSE_YAW missing) and carries a distinct y
    rig.peers.send_plant(vx=10.0, x=0.5, y=7.0, skip=(FrameId.VEH_POSE_YAW,))
    rig.tick(50, plant=None)
    used = rig.controller.samples[-1]
    print("y used at 50:", used.y, "(torn set had y = 7.0)")
    assert used.y == pytest.approx(0.04, abs=1e-6)               # the complete sample of 40 ms
    rig.run(55, 75)
    assert rig.diag_at(75).faults & 0b0001                       # torn set detected at 60
    assert all(sample.y != pytest.approx(7.0) for sample in rig.controller.samples)
    assert rig.ecu.rx_counts["torn"] == 1


def test_e2e_error_sets_faults_bit_1_for_one_cycle(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 30)
    good = bytearray(encode(VehDyn(10.0, 0.0, 0.0), rig.peers.plant_counter))
    good[0] ^= 0xFF                                              # corrupt the CRC
    rig.peers.send_raw(FrameId.VEH_DYN, bytes(good))
    rig.peers.send_raw(FrameId.PLANNER_REQ, b"\x00\x01")         # wrong length
    rig.run(35, 75)
    faults = {t: rig.diag_at(t).faults for t in (25, 50, 75)}
    print("FAULTS by cycle:", {t: f"{f:04b}" for t, f in faults.items()})
    assert not faults[25] & 0b0010
    assert faults[50] & 0b0010
    assert not faults[75] & 0b0010                               # not latched
    assert rig.ecu.rx_counts["rejected"] == 2


def test_bad_tick_and_short_sync_are_discarded_and_not_acked(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 20)
    rig.peers.send_sync(23)                                      # not a multiple of 5
    rig.peers.send_raw(FrameId.HIL_SYNC, b"\x19\x00")            # 2 bytes
    pump(rig.ecu, rig.ecu_bus)
    assert rig.peers.received() == []
    rig.run(25, 25)
    assert rig.diag_at(25).faults & 0b0010


# ------------------------------------------------------------------ guard and failures
@pytest.mark.parametrize("failure", ["nan", "raise", "too_much_steer", "too_much_torque"])
def test_refused_or_failed_command_becomes_fallback_with_bit_2(buses, failure):
    controller = ScriptedController(gain=-1.0)
    rig = Rig(*buses, controller=controller)
    rig.handshake()
    rig.run(0, 50)
    held = rig.command_at(50).steer_angle_cmd
    if failure == "nan":
        controller.nan_command = True
    elif failure == "raise":
        controller.raise_on_step = True
    elif failure == "too_much_steer":
        controller.command_override = Command(0.5, 100.0)
    else:
        controller.command_override = Command(0.0, 5000.0)
    rig.run(55, 75)
    command, diag = rig.command_at(75), rig.diag_at(75)
    print(f"{failure}: sent steer {command.steer_angle_cmd} (held {held}), torque "
          f"{command.drive_torque_cmd}, FAULTS {diag.faults:04b}")
    assert command.ctrl_mode is CtrlMode.ACTIVE and command.cmd_valid
    assert command.steer_angle_cmd == pytest.approx(held, abs=1e-4)
    assert command.drive_torque_cmd == 0.0
    assert diag.faults & 0b0100
    assert not rig.diag_at(50).faults & 0b0100


FAILURES = {"law_fallback": "fall_back", "raise": "raise_on_step", "nan": "nan_command"}


@pytest.mark.parametrize("failure", FAILURES)
def test_a_controller_falling_back_on_4_tasks_in_a_row_ends_in_safe_stop(buses, failure):
    """Contract rev. 2, a failing controller: the law's own fallback, an exception or a
    refused command on 4 control tasks in a row (FAULTS bit 2, steer held) -> SAFE_STOP at
    the 5th, steering back towards straight at 0.2 rad/s and braking, CMD_VALID = 1; the
    planner's ENGAGE = 1 does not bring ACTIVE back."""
    controller = ScriptedController(gain=-1.0)
    rig = Rig(*buses, controller=controller)
    rig.handshake()
    rig.run(0, 50)
    held = rig.command_at(50).steer_angle_cmd
    setattr(controller, FAILURES[failure], True)
    rig.run(55, 300)
    tasks = range(75, 301, 25)
    sent = [rig.command_at(t) for t in tasks]
    faults = [rig.diag_at(t).faults for t in tasks]
    print(f"{failure}: held {held}; modes {[c.ctrl_mode.name for c in sent]}; "
          f"steer {[c.steer_angle_cmd for c in sent]}")
    assert [c.ctrl_mode for c in sent] == [CtrlMode.ACTIVE] * 4 + [CtrlMode.SAFE_STOP] * (len(tasks) - 4)
    assert all(f & 0b0100 for f in faults[:4]) and not any(f & 0b0100 for f in faults[4:])
    assert all(c.cmd_valid for c in sent)
    step = 0.2 * 0.025   # the safe stop's rate over one task
    assert [c.steer_angle_cmd for c in sent] == pytest.approx(
        [held] * 4 + [held + k * step for k in range(1, len(tasks) - 3)], abs=1e-4)
    assert all(c.drive_torque_cmd == -1500.0 for c in sent[4:])
    steps_by_the_law = len(controller.samples)
    rig.run(305, 350)   # SAFE_STOP runs no law
    assert len(controller.samples) == steps_by_the_law
    assert rig.command_at(350).ctrl_mode is CtrlMode.SAFE_STOP


def test_fallbacks_broken_by_a_good_step_keep_active(buses):
    """3 fallbacks in every 4 tasks are no failing controller: a good step ends the streak."""
    controller = ScriptedController(gain=-1.0)
    rig = Rig(*buses, controller=controller)
    rig.handshake()
    rig.run(0, 50)
    for t in range(55, 405, 5):
        controller.fall_back = (t // 25) % 4 != 0
        rig.tick(t)
    tasks = range(75, 401, 25)
    fallbacks = sum(bool(rig.diag_at(t).faults & 0b0100) for t in tasks)
    print(f"{fallbacks} fallbacks in {len(tasks)} tasks")
    assert fallbacks == 3 * len(tasks) // 4
    assert all(rig.command_at(t).ctrl_mode is CtrlMode.ACTIVE for t in tasks)


def test_after_a_failing_controllers_safe_stop_the_ecu_engages_afresh_through_standby(buses):
    """SAFE_STOP for a failing controller is left as any SAFE_STOP: at standstill on
    ENGAGE = 0 (STANDBY); ENGAGE = 1 again engages a controller that works again and keeps
    it ACTIVE (no streak of fallbacks carried over)."""
    controller = ScriptedController(gain=-1.0, fall_back=True)
    rig = Rig(*buses, controller=controller)
    rig.handshake()
    rig.run(0, 175)
    assert rig.command_at(175).ctrl_mode is CtrlMode.SAFE_STOP
    at_rest = lambda t: {"vx": 0.0, "x": 1.75, "y": 0.175}   # noqa: E731
    rig.run(180, 225, plant=at_rest, planner=lambda t: {"engage": False})
    assert rig.command_at(225).ctrl_mode is CtrlMode.STANDBY
    controller.fall_back = False
    rig.run(230, 400, plant=at_rest)
    modes = [rig.command_at(t).ctrl_mode for t in range(250, 401, 25)]
    assert modes == [CtrlMode.ACTIVE] * len(modes)


def test_load_failure_latches_fault_with_cmd_valid_0(buses):
    ecu_bus, peer_bus = buses

    def broken_factory(name: str):
        raise FileNotFoundError("models/artifacts/dk_d5.npz")

    ecu = Ecu(ecu_bus, "eso-dkmpc", PATHS, lockstep=True, controller_factory=broken_factory,
              path_loader=load_path)
    peers = PeerNodes(peer_bus)
    peers.send_handshake()
    pump(ecu, ecu_bus)
    assert ack_ticks(peers.received()) == [HANDSHAKE_TICK]
    for t in range(0, 55, 5):
        if t % 10 == 0:
            peers.send_plant(**moving_plant(t))
        if t % 25 == 0:
            peers.send_planner()
        peers.send_sync(t)
        pump(ecu, ecu_bus)
    sent = commands(peers.received())
    print("load error:", ecu.load_error, "modes:", [c.ctrl_mode.name for c in sent])
    assert [c.ctrl_mode for c in sent] == [CtrlMode.FAULT] * 3
    assert not any(c.cmd_valid for c in sent)


def test_non_contract_and_extended_frames_are_ignored(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.peers.bus.send(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))
    rig.peers.bus.send(can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=True))
    rig.run(0, 25)
    assert rig.ecu.rx_counts["rejected"] == 0
    assert not rig.diag_at(25).faults & 0b0010


# ------------------------------------------------------------------ determinism and threads
TIMING_FIELDS = ("solve_time_us", "cycle_time_us", "overruns")


def scripted_run(ecu_bus: can.BusABC, peer_bus: can.BusABC) -> list[can.Message]:
    rig = Rig(ecu_bus, peer_bus)
    rig.handshake()
    sent = rig.run(0, 200, plant=lambda t: moving_plant(t) if t < 90 or t > 160 else None)
    rig.ecu.close()
    return sent


def test_lockstep_frames_are_bit_for_bit_repeatable_apart_from_timing_fields():
    runs = []
    for _ in range(2):
        channel = f"ecu-determinism-{uuid.uuid4()}"
        with can.Bus(interface="virtual", channel=channel) as ecu_bus, \
                can.Bus(interface="virtual", channel=channel) as peer_bus:
            runs.append(scripted_run(ecu_bus, peer_bus))
    first, second = runs
    assert len(first) == len(second) > 40
    differing_payloads = 0
    for a, b in zip(first, second):
        assert a.arbitration_id == b.arbitration_id
        if a.arbitration_id == FrameId.CTRL_DIAG:
            da, db = decode(a.arbitration_id, bytes(a.data)), decode(b.arbitration_id, bytes(b.data))
            assert da.counter == db.counter
            for name in ("qp_status", "qp_iter", "faults"):
                assert getattr(da.frame, name) == getattr(db.frame, name)
            differing_payloads += bytes(a.data) != bytes(b.data)
        else:
            assert bytes(a.data) == bytes(b.data)
    print(f"{len(first)} frames compared; CTRL_DIAG payloads differing only in timing: "
          f"{differing_payloads}")


def test_run_loop_in_a_thread_answers_ticks(buses):
    ecu_bus, peer_bus = buses
    controller = ScriptedController()
    ecu = Ecu(ecu_bus, "scripted", PATHS, lockstep=True,
              controller_factory=lambda name: controller, path_loader=load_path)
    peers = PeerNodes(peer_bus)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,))
    thread.start()

    def wait_ack(tick: int) -> list[can.Message]:
        got: list[can.Message] = []
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            message = peer_bus.recv(0.1)
            if message is None:
                continue
            got.append(message)
            if ack_ticks([message]) == [tick]:
                return got
        raise AssertionError(f"no ACK for {tick}")

    try:
        peers.send_handshake()
        wait_ack(HANDSHAKE_TICK)
        sent = []
        for t in range(0, 55, 5):
            if t % 10 == 0:
                peers.send_plant(**moving_plant(t))
            if t % 25 == 0:
                peers.send_planner()
            peers.send_sync(t)
            sent += wait_ack(t)
    finally:
        stop.set()
        thread.join(2.0)
        ecu.close()
    print("modes:", [c.ctrl_mode.name for c in commands(sent)])
    assert [c.ctrl_mode for c in commands(sent)] == [CtrlMode.STANDBY, CtrlMode.ACTIVE, CtrlMode.ACTIVE]
    assert not thread.is_alive()


def test_close_sends_one_last_invalid_command_and_shuts_the_bus(buses):
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 50)
    rig.ecu.close()
    rig.ecu.close()  # idempotent
    last = commands(rig.peers.received())
    print("after close:", last)
    assert len(last) == 1 and not last[0].cmd_valid and last[0].drive_torque_cmd == 0.0
    assert rig.ecu_bus._is_shutdown
    assert math.isclose(last[0].steer_angle_cmd, rig.command_at(50).steer_angle_cmd, abs_tol=1e-4)


def test_real_lmpc_and_csv_path_through_the_ecu_are_repeatable(tmp_path):
    """The registry's LMPC and ReferencePath.from_csv (the ECU's defaults), twice: the
    command frames are identical bit for bit and the law really steers."""
    path_file = tmp_path / "straight.csv"
    path_file.write_text("x,y,yaw\n" + "".join(f"{0.5 * i:.3f},0.0,0.0\n" for i in range(201)))
    runs = []
    for _ in range(2):
        channel = f"ecu-lmpc-{uuid.uuid4()}"
        with can.Bus(interface="virtual", channel=channel) as ecu_bus, \
                can.Bus(interface="virtual", channel=channel) as peer_bus:
            ecu = Ecu(ecu_bus, "lmpc", {1: path_file}, lockstep=True)
            assert ecu.load_error is None, ecu.load_error
            peers = PeerNodes(peer_bus)
            peers.send_handshake()
            pump(ecu, ecu_bus)
            sent = []
            for t in range(0, 305, 5):
                if t % 10 == 0:   # 0.3 m left of the path, driving along it at 10 m/s
                    peers.send_plant(vx=10.0, x=5.0 + 0.01 * t, y=0.3)
                if t % 25 == 0:
                    peers.send_planner(True, 10.0, 1)
                peers.send_sync(t)
                pump(ecu, ecu_bus)
                sent += peers.received()
            ecu.close()
            runs.append(sent)
    first, second = ([bytes(m.data) for m in run if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
                     for run in runs)
    steer = [c.steer_angle_cmd for c in commands(runs[0])]
    modes = [c.ctrl_mode.name for c in commands(runs[0])]
    print("modes:", modes, "\nsteer [rad]:", steer)
    assert first == second and len(first) == 13
    assert modes[1:] == ["ACTIVE"] * 12
    assert all(s < 0 for s in steer[1:4])      # steers right, back towards y = 0
    assert all(d.qp_status is QpStatus.SOLVED for d in diags(runs[0])[1:])

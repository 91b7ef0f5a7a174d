"""`make faults`: every fault of hil/faults.py in the high-mu double lane change, in
lockstep on the virtual bus, judged from the frames alone.

Per run (`evaluate`):

- the ECU's mode sequence and FAULTS bits, from its STEER_TORQUE_CMD / CTRL_DIAG frames;
- time to detect: first control cycle at or after the fault's first action (the tick at
  which the injector first changed a frame; t = 0 for vehicle faults) with a mode other
  than ACTIVE or a FAULTS bit that was clear in the cycle before the onset;
- each expected reaction of the contract (``Expect``: a mode or a FAULTS bit) and whether it
  came within its bound;
- max |e_Y| of the true pose (t = 0, 25, 50, ... ms) and the outcome: ``safe stop`` (SAFE_STOP
  and the plant at standstill at the end; SAFE_STOP steers straight, so it may leave the
  path), else ``tracked`` (max |e_Y| <= 1 m), else ``FAILED``;
- invalid commands, checked independently of the ECU's own code: every ECU frame decoded
  with cantools from the DBC, CRC recomputed; a STEER_TORQUE_CMD with CMD_VALID = 1 is
  invalid when its CRC is wrong, |steer| > 0.3 rad, |torque| > the ECU's 3000 N m (inside
  the DBC's range), its CTRL_MODE is not ACTIVE / DEGRADED / SAFE_STOP, or it drives
  (torque > 0) in SAFE_STOP;
- crashes: the run raised (ECU thread died, ACK timeout) or the ECU logged an
  "unexpected error" (an exception its RX / control path caught).

Bus faults run with ESO-DKMPC; vehicle faults with ESO-DKMPC and DKMPC (the observer is
what should make them survivable). The full 13.5 s scenario every time (about 12-15 s of
wall clock per run here); faults start at 3.0 s, in the first lane change (X ~ 29 m).

``--ecu c`` (``make faults-c``) runs the same cases against the C ECU executable
(``build/firmware/ecu``) as ``hil run --ecu c`` does: a separate process on a socketcand hub
of its own on TCP loopback, the injector between this process's nodes and the hub. It
writes results/faults_c.* and compares each verdict with the Python campaign's
(results/faults.json). The lost bus drops the process's connection at a relay
(`_DroppingRelay`) and watches its output and CPU time. A case whose frames cannot reach a
separate process is reported as not applicable with the reason (`c_not_applicable`). A
crash of the C ECU is the run raising (the process exited or stopped ACKing); it has no
Python exceptions to count.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import socket
import sys
import threading
import time
import types
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from can_defs.frames import HANDSHAKE_TICK, CtrlMode, FrameId
from hil.errors import HilError
from hil.faults import PLANNER_IDS, PLANT_IDS, FaultSpec

#: Where the fault starts in the campaign (s): mid first lane change of the DLC.
ONSET_S = 3.0
#: Lateral deviation the vehicle must stay within (m) unless it comes to a safe stop.
PATH_TOLERANCE_M = 1.0
#: Limits of the independent command check (contract / ECU configuration).
STEER_LIMIT_RAD = 0.3
TORQUE_LIMIT_NM = 3000.0
STANDSTILL_MPS = 0.1
CONTROL_PERIOD_MS = 25
#: Window at the end of a run over which the remaining |e_Y| is averaged (s): the straight
#: after the manoeuvre, where a steady-state offset shows.
SETTLE_WINDOW_S = 2.0
VALID_MODES = {int(CtrlMode.ACTIVE), int(CtrlMode.DEGRADED), int(CtrlMode.SAFE_STOP)}
#: The campaign's scenario and the files it writes into its output folder.
SCENARIO = "dlc_high_mu"
RESULT_FILES = ("faults.md", "faults.json", "faults_vehicle.png")
#: The ECU implementations the campaign can drive (``hil.session.ECU_IMPLEMENTATIONS``).
ECUS = ("python", "c")
#: Look-alike frame kinds the C ECU's loopback socketcand hub cannot carry as themselves.
HUB_LOST_KINDS = ("fd", "remote", "error")


def result_files(ecu: str = "python") -> tuple[str, ...]:
    """The files the campaign writes for ``ecu``: faults.* (Python), faults_c.* (C)."""
    if ecu == "python":
        return RESULT_FILES
    return tuple(name.replace("faults", f"faults_{ecu}", 1) for name in RESULT_FILES)


@dataclass(frozen=True)
class Expect:
    """An expected reaction within ``bound_ms`` of the fault's first action, and why that
    bound (contract rule): ``mode`` entered, FAULTS ``bit`` set, ``recover`` (ACTIVE again
    after the reaction) or ``quiet`` (no reaction at all: mode ACTIVE and none of the bus
    bits 0, 1, 3 newly set for the whole ``bound_ms``)."""

    bound_ms: int
    why: str
    mode: CtrlMode | None = None
    bit: int | None = None
    recover: bool = False
    quiet: bool = False

    def label(self) -> str:
        if self.quiet:
            return f"no reaction for {self.bound_ms} ms"
        if self.recover:
            return f"ACTIVE again <= {self.bound_ms} ms"
        what = self.mode.name if self.mode is not None else f"bit {self.bit}"
        return f"{what} <= {self.bound_ms} ms"


# Contract bounds (can-contract.md, fault reaction), counted from the first frame the
# fault hit (t0, a plant instant): the last good sample is then t0 - 10 ms, its age passes
# 20 ms after t0 + 10 ms and the next control task is at most 25 ms later.
DEGRADED = Expect(35, "sample > 20 ms old at a task", mode=CtrlMode.DEGRADED)
# SAFE_STOP: age > 100 ms after t0 + 90 ms, plus up to 25 ms to the next task.
SAFE_STOP = Expect(115, "no good sample > 100 ms", mode=CtrlMode.SAFE_STOP)
# E2E error: flagged in the next CTRL_DIAG (the frame is handled before the next task).
E2E_NEXT = Expect(25, "E2E error in the next CTRL_DIAG", bit=1)
# Evidence one plant period (10 ms) after the first action (the next sample shows the gap).
E2E_NEXT_SAMPLE = Expect(35, "sequence error seen with the next sample", bit=1)
TORN = Expect(35, "torn set seen with the next sample", bit=0)
STANDBY_PLANNER = Expect(25, "unknown PATH_ID / ENGAGE = 0 at the next task",
                         mode=CtrlMode.STANDBY)
# PLANNER_REQ every 25 ms on the control grid; the last one 25 ms before the first
# missing, so its age passes 100 ms at the task t0 + 100 ms.
STANDBY_TIMEOUT = Expect(100, "PLANNER_REQ missing > 100 ms", mode=CtrlMode.STANDBY)
# Rev. 2, plausibility: an implausible sample is not a good sample (handled as a torn one):
# FAULTS bit 0 in the CTRL_DIAG of the task that follows it.
IMPLAUSIBLE = Expect(25, "implausible sample flagged at the next task", bit=0)
# Rev. 2, frame kinds: CAN FD / extended / remote / error frames are ignored, never FAULTS.
IGNORED = Expect(1000, "other frame kinds ignored, never in FAULTS", quiet=True)
# Rev. 2, jump of virtual time: at the jump TICK (a control instant here) STANDBY with
# CMD_VALID = 0 and bits 1 and 3; re-engaged by the usual rule (next fresh sample, 10 ms,
# then the next task, at most 25 ms later).
JUMP_STANDBY = Expect(0, "STANDBY at the jump TICK", mode=CtrlMode.STANDBY)
JUMP_BIT_1 = Expect(0, "bit 1 in the next CTRL_DIAG", bit=1)
JUMP_BIT_3 = Expect(0, "bit 3 (controller/observer reset) in the next CTRL_DIAG", bit=3)
JUMP_REENGAGE = Expect(35, "re-engaged by the usual rule", recover=True)
# Lockstep: a lost bus stops virtual time (no tick arrives), so once the bus is back the
# run goes on with no reaction in virtual time.
LOCKSTEP_PAUSE = Expect(500, "lockstep: no tick while the bus is lost, no input timeout",
                        quiet=True)
# A replay of 1 s whose counters read as next is accepted once its positions are
# continuous; when the real frames return 1 s later their position is not continuous with
# the replayed one for 100 ms, so the next is a restarted reference (lost): SAFE_STOP.
REPLAY_END = Expect(1000 + 115, "real frames back: no continuous sample for 100 ms",
                    mode=CtrlMode.SAFE_STOP)
#: Bus bits whose new appearance counts as a reaction (bit 2 is the solver's fallback).
REACTION_BITS = 0b1011


@dataclass(frozen=True)
class FaultCase:
    """One campaign entry: its ``[faults]`` table, controllers and expected reactions."""

    name: str
    group: str                      # "bus" or "vehicle"
    table: dict[str, Any]
    controllers: tuple[str, ...]
    expects: tuple[Expect, ...] = ()
    note: str = ""
    #: A fault of the time base or of the ECU's own bus (`ecu_cases`), run by
    #: `run_ecu_case`: ``{"kind": "time_jump", "start_s", "ahead_ms"}`` or
    #: ``{"kind": "lost_bus", "start_s", "outage_s"}``; None: the injector's ``table``.
    ecu_fault: dict[str, Any] | None = None


def _bus(kind: str, expects: tuple[Expect, ...] = (), note: str = "", name: str | None = None,
         **fault: Any) -> FaultCase:
    fault = {"kind": kind, "start_s": ONSET_S, **fault}
    return FaultCase(name or kind, "bus", {"seed": 1, "bus": [fault]}, ("eso-dkmpc",), expects, note)


def _lookalikes(name: str, frame_kind: str, sync_tick: int, note: str,
                also: str | None = None) -> FaultCase:
    """Look-alikes of every frame the ECU receives (plant and planner), for 1 s."""
    ids = list(PLANT_IDS + PLANNER_IDS)
    faults = [{"kind": "lookalike", "ids": ids, "frame_kind": kind, "start_s": ONSET_S,
               "duration_s": 1.0, "sync_tick": sync_tick if kind == frame_kind else -1}
              for kind in (frame_kind, also) if kind is not None]
    return FaultCase(name, "bus", {"seed": 1, "bus": faults}, ("eso-dkmpc",), (IGNORED,), note)


def _vehicle(name: str, table: dict[str, Any], note: str = "") -> FaultCase:
    return FaultCase(name, "vehicle", table, ("eso-dkmpc", "dkmpc"), (), note)


def campaign_cases() -> list[FaultCase]:
    """The faults of `make faults`, bus faults first."""
    return [
        _bus("drop", (TORN,), "5 % of plant frames lost", name="drop 5 %", rate=0.05),
        _bus("drop", (DEGRADED,), "bursts of 6 frames of one ID (60 ms)", name="drop bursts",
             rate=0.02, burst=6),
        _bus("delay", (), "no timestamp in the contract: undetectable", delay_ms=20),
        _bus("duplicate", (E2E_NEXT,), "every plant frame twice (repeated CNT)", rate=1.0),
        _bus("reorder", (E2E_NEXT_SAMPLE,), "10 % of sample instants swapped with the next",
             rate=0.1),
        _bus("bitflip", (E2E_NEXT,), "one bit of 5 % of plant frames", rate=0.05),
        _bus("frozen_counter", (DEGRADED, SAFE_STOP), "plant CNT stuck from 3.0 s on"),
        _bus("wrong_crc", (E2E_NEXT, DEGRADED), "every plant frame for 50 ms", duration_s=0.05),
        _bus("silent", (DEGRADED,), "plant silent 60 ms", name="plant silent 60 ms",
             duration_s=0.06),
        _bus("silent", (DEGRADED, SAFE_STOP), "plant silent from 3.0 s on",
             name="plant silent"),
        _bus("silent", (STANDBY_TIMEOUT,), "planner silent 200 ms", name="planner silent 200 ms",
             sender="planner", duration_s=0.2),
        _bus("babble", (DEGRADED, SAFE_STOP), "0x0FF back to back for 300 ms starves 0x100-0x110",
             name="babble 0x0FF", babble_id=0x0FF, frames_per_tick=10, starve=True,
             duration_s=0.3),
        _bus("babble", (E2E_NEXT,), "random payloads on VEH_DYN's ID for 1 s",
             name="babble on 0x100", babble_id=0x100, frames_per_tick=10, starve=False,
             duration_s=1.0),
        _bus("override", (DEGRADED, IMPLAUSIBLE), "VX 327 m/s (valid CRC) for 50 ms",
             name="VX 327 m/s", field="vx", value=327.0, duration_s=0.05),
        _bus("override", (DEGRADED, IMPLAUSIBLE, SAFE_STOP),
             "VX raw max (327.67 m/s) for 100 ms: the next good sample is > 100 ms after the "
             "last, a restarted reference (SAFE_STOP)", name="VX out of range",
             field="vx", value=1e9, duration_s=0.1),
        _bus("override", (DEGRADED, IMPLAUSIBLE), "YAW 4 rad, outside [-pi, pi), for 50 ms",
             name="YAW 4 rad", field="yaw", value=4.0, duration_s=0.05),
        _bus("override", (IMPLAUSIBLE,), "one sample with POS_X 5 km away",
             name="position jump 5 km", field="pos_x", value=5000.0, duration_s=0.01),
        _bus("override", (DEGRADED, IMPLAUSIBLE, SAFE_STOP),
             "POS_X 5 km away from 3.0 s on: not continuous for 100 ms, then a restarted "
             "reference", name="position 5 km off", field="pos_x", value=5000.0),
        _bus("override", (), "VX = 0 (division by Vx) for 100 ms", name="VX = 0",
             field="vx", value=0.0, duration_s=0.1),
        _bus("override", (), "TARGET_SPEED raw max (655.35 m/s) for 100 ms",
             name="TARGET_SPEED max", sender="planner", field="target_speed", value=1e9,
             duration_s=0.1),
        _bus("override", (STANDBY_PLANNER,), "PATH_ID 99 for 200 ms", name="unknown PATH_ID",
             sender="planner", field="path_id", value=99, duration_s=0.2),
        _bus("engage_toggle", (STANDBY_PLANNER,), "ENGAGE 0/1 every 50 ms for 0.5 s",
             sender="planner", period_ms=50, duration_s=0.5),
        _lookalikes("CAN FD look-alikes", "fd", HANDSHAKE_TICK,
                    "FD copies (next CNT, valid CRC) of every plant/planner frame and an FD "
                    "HIL_SYNC with the handshake value, each tick for 1 s"),
        _lookalikes("extended-ID look-alikes", "extended", 60_000,
                    "29-bit copies of every plant/planner frame and a 29-bit HIL_SYNC "
                    "60 s ahead, each tick for 1 s"),
        _lookalikes("remote and error frames", "remote", -1,
                    "remote frames on the plant/planner IDs plus error frames, 1 s",
                    also="error"),
        _bus("replay", (E2E_NEXT,), "the plant's frames of 1 s earlier re-sent after the "
             "real ones (old CNT and CRC) for 1 s", name="stale replay", age_ms=1000,
             duration_s=1.0),
        _bus("replay", (DEGRADED, IMPLAUSIBLE, REPLAY_END), "the plant replaced by its own "
             "frames of 160 ms earlier (16 instants: CNT reads as next) for 1 s: only the "
             "position steps where the replay starts and ends show",
             name="replay, CNT as next", age_ms=160, replace=True, duration_s=1.0),
        _vehicle("none", {}, "baseline"),
        _vehicle("mu step 0.85 -> 0.5", {"mu_step": {"time_s": ONSET_S, "mu": 0.5}},
                 "at 3.0 s"),
        _vehicle("mass +200 kg", {"vehicle": {"mass_offset_kg": 200.0}}),
        _vehicle("steer offset 0.02 rad", {"vehicle": {"steer_offset_rad": 0.02}}),
        _vehicle("steer lag +0.1 s", {"vehicle": {"steer_extra_lag_s": 0.1}}),
        _vehicle("sensor bias + noise", {"seed": 1, "sensor": {
            "vy_bias": 0.05, "vy_noise": 0.02, "yaw_rate_bias": 0.01, "yaw_rate_noise": 0.005}},
            "VY +0.05 (sd 0.02) m/s, YAW_RATE +0.01 (sd 0.005) rad/s"),
        _vehicle("all vehicle faults", {"seed": 1, "mu_step": {"time_s": ONSET_S, "mu": 0.5},
                 "vehicle": {"mass_offset_kg": 200.0, "steer_offset_rad": 0.02,
                             "steer_extra_lag_s": 0.1},
                 "sensor": {"vy_bias": 0.05, "vy_noise": 0.02, "yaw_rate_bias": 0.01,
                            "yaw_rate_noise": 0.005}}, "the five above at once"),
    ]


def ecu_cases() -> list[FaultCase]:
    """Faults no HIL node's frame can carry (contract rev. 2): a jump of virtual time (the
    time master's HIL_SYNC far ahead) and a lost bus (the ECU's interface goes down)."""
    return [
        FaultCase("virtual time jump", "bus", {}, ("eso-dkmpc",),
                  (JUMP_STANDBY, JUMP_BIT_1, JUMP_BIT_3, JUMP_REENGAGE),
                  "HIL_SYNC 10 s ahead from 3.0 s on: the ECU's clock jumps once",
                  ecu_fault={"kind": "time_jump", "start_s": ONSET_S, "ahead_ms": 10_000}),
        FaultCase("lost bus", "bus", {}, ("eso-dkmpc",), (LOCKSTEP_PAUSE,),
                  "the ECU's interface down for 2.5 s of wall clock at 3.0 s (every receive "
                  "and send fails), then back",
                  ecu_fault={"kind": "lost_bus", "start_s": ONSET_S, "outage_s": 2.5}),
    ]


def all_cases() -> list[FaultCase]:
    """Every case of `make faults`: the injector's (`campaign_cases`, also the campaign
    grid's fault catalogue) and the ECU-level ones (`ecu_cases`)."""
    return campaign_cases() + ecu_cases()


# --- judging one run ----------------------------------------------------------------------


@dataclass
class Verdict:
    """What one run showed (see the module docstring)."""

    case: str
    group: str
    controller: str
    description: str
    mode_sequence: str = ""
    detect_ms: int | None = None
    expects: list[dict[str, Any]] = field(default_factory=list)
    max_abs_ey_m: float = math.nan
    settled_abs_ey_m: float = math.nan   # mean |e_Y| over the last 2 s (steady-state offset)
    outcome: str = ""
    invalid_commands: int = 0
    commands_checked: int = 0
    crashes: int = 0
    crash_reason: str = ""
    controller_errors: int = 0
    faults_first_ms: int | None = None
    frames_hit: int = 0
    wall_s: float = 0.0
    e_y: list[float] = field(default_factory=list)
    time_s: list[float] = field(default_factory=list)
    #: Which ECU ran ("python", "c").
    ecu: str = "python"
    #: Why this case cannot run against this ECU ("" when it ran): reported, not dropped.
    not_applicable: str = ""

    @property
    def expects_met(self) -> bool:
        return all(e["met"] for e in self.expects)

    def passed(self) -> bool:
        """No crash, no invalid command, outcome tracked or safe stop, expectations met
        (False for a case that did not run: ``not_applicable``)."""
        return (not self.not_applicable and self.crashes == 0 and self.invalid_commands == 0
                and self.outcome in ("tracked", "safe stop") and self.expects_met)


def check_commands(raw: Sequence[tuple[int, int, bytes]]) -> tuple[int, int, list[str]]:
    """Independent check of the ECU's commands: (invalid count, CMD_VALID = 1 frames checked,
    reasons of the first few). ``raw``: (tick ms, arbitration ID, payload) of ECU frames."""
    import cantools

    from can_defs.crc import e2e_crc
    from can_defs.dbc import DBC_PATH

    db = cantools.database.load_file(str(DBC_PATH))
    message = db.get_message_by_frame_id(int(FrameId.STEER_TORQUE_CMD))
    invalid, checked, reasons = 0, 0, []
    for tick, frame_id, data in raw:
        if frame_id != FrameId.STEER_TORQUE_CMD:
            continue
        why = None
        if len(data) != 8:
            why = f"length {len(data)}"
        else:
            s = message.decode(data, decode_choices=False)
            if not s["CMD_VALID"]:
                continue
            checked += 1
            steer, torque, mode = s["STEER_ANGLE_CMD"], s["DRIVE_TORQUE_CMD"], int(s["CTRL_MODE"])
            if data[0] != e2e_crc(frame_id, data):
                why = "CRC"
            elif not (math.isfinite(steer) and abs(steer) <= STEER_LIMIT_RAD + 1e-9):
                why = f"steer {steer}"
            elif not (math.isfinite(torque) and abs(torque) <= TORQUE_LIMIT_NM + 1e-9):
                why = f"torque {torque}"
            elif mode not in VALID_MODES:
                why = f"CMD_VALID in mode {mode}"
            elif mode == CtrlMode.SAFE_STOP and torque > 0:
                why = f"drive torque {torque} in SAFE_STOP"
        if why is not None:
            invalid += 1
            if len(reasons) < 5:
                reasons.append(f"t={tick} ms: {why}")
    return invalid, checked, reasons


def mode_sequence(times_s: np.ndarray, modes: np.ndarray, max_items: int = 7) -> str:
    """Run-length mode sequence, ``ACTIVE, DEGRADED@3.025, ...`` (startup INIT / STANDBY
    before the first ACTIVE left out)."""
    names = [CtrlMode(int(m)).name for m in modes]
    start = next((i for i, n in enumerate(names) if n == "ACTIVE"), 0)
    items: list[str] = []
    previous = None
    for t, name in zip(times_s[start:], names[start:]):
        if name != previous:
            items.append(name if previous is None else f"{name}@{t:.3f}")
            previous = name
    if len(items) > max_items:
        items = items[:max_items - 1] + [f"... ({len(items) - max_items + 1} more)"]
    return ", ".join(items)


def evaluate(case: FaultCase, controller: str, result: Any, error: BaseException | None,
             unexpected_errors: int, controller_errors: int, description: str,
             path: Any = None, onset_ms: int | None = None, frames_hit: int = 0) -> Verdict:
    """Judge one run (``result`` a ``hil.session.HilRunResult``, None when it raised;
    ``path`` the reference path, to keep e_Y(t) for the figure; ``onset_ms`` the fault's
    first action and ``frames_hit`` what it acted on, taken from the run's injector when
    not given)."""
    verdict = Verdict(case.name, case.group, controller, description,
                      controller_errors=controller_errors)
    if error is not None or result is None:
        verdict.crashes = 1
        verdict.crash_reason = f"{type(error).__name__}: {error}"
        verdict.outcome = "CRASH"
        verdict.expects = [{"expect": e.label(), "why": e.why, "at_ms": None, "met": False}
                           for e in case.expects]
        return verdict
    verdict.wall_s = result.wall_time_s
    if unexpected_errors:
        verdict.crashes = unexpected_errors
        verdict.crash_reason = f"{unexpected_errors} exception(s) caught inside the ECU"
    ecu, plant = result.ecu_trace, result.plant_trace
    times, modes, faults = ecu["time"], ecu["ctrl_mode"].astype(int), ecu["faults"].astype(int)
    verdict.mode_sequence = mode_sequence(times, modes)
    injector = result.extra.get("injector")
    if injector is not None:
        onset_ms = injector.first_action_ms
        frames_hit = sum(r.actions for r in injector.records())
    if case.group == "vehicle":
        onset_ms = None  # no bus evidence: the ECU is not expected to detect these
    verdict.faults_first_ms = onset_ms
    verdict.frames_hit = frames_hit
    tick_ms = np.round(times * 1000).astype(int)
    if onset_ms is not None and len(times):
        after = tick_ms >= onset_ms
        before = np.flatnonzero(~after)
        baseline = faults[before[-1]] if len(before) else 0
        changed = after & ((modes != int(CtrlMode.ACTIVE)) | ((faults & ~baseline) != 0))
        if changed.any():
            verdict.detect_ms = int(tick_ms[np.argmax(changed)] - onset_ms)
        reaction = after & ((modes != int(CtrlMode.ACTIVE)) | ((faults & ~baseline & REACTION_BITS) != 0))
        for expect in case.expects:
            verdict.expects.append(_judge(expect, tick_ms - onset_ms, after, modes, faults, reaction))
    elif case.expects:
        verdict.expects = [{"expect": e.label(), "why": e.why, "at_ms": None, "met": False}
                           for e in case.expects]
    verdict.max_abs_ey_m = float(result.tracking.lateral.max_abs)
    safe_stopped = (modes == int(CtrlMode.SAFE_STOP)).any() and abs(plant["vx"][-1]) < STANDSTILL_MPS
    if safe_stopped:
        verdict.outcome = "safe stop"
    elif verdict.max_abs_ey_m <= PATH_TOLERANCE_M:
        verdict.outcome = "tracked"
    else:
        verdict.outcome = "FAILED"
    raw = result.extra.get("ecu_frames_raw", [])
    verdict.invalid_commands, verdict.commands_checked, reasons = check_commands(raw)
    if reasons:
        verdict.crash_reason += ("; " if verdict.crash_reason else "") + "invalid: " + "; ".join(reasons)
    if path is not None:
        _keep_ey(verdict, result, path)
    return verdict


def _judge(expect: Expect, since_ms: np.ndarray, after: np.ndarray, modes: np.ndarray,
           faults: np.ndarray, reaction: np.ndarray) -> dict[str, Any]:
    """One expectation against the cycles of a run (``since_ms`` each cycle's time after the
    onset; ``after`` the cycles from the onset on; ``reaction`` those with a mode other than
    ACTIVE or a newly set bus bit)."""
    if expect.quiet:
        window = after & (since_ms <= expect.bound_ms)
        hit = reaction & window
        at = int(since_ms[np.argmax(hit)]) if hit.any() else None
        return {"expect": expect.label(), "why": expect.why, "at_ms": at,
                "met": bool(at is None and window.any())}
    if expect.recover:
        first = np.flatnonzero(after & (modes != int(CtrlMode.ACTIVE)))
        hit = np.zeros_like(after)
        if len(first):
            hit[first[0]:] = modes[first[0]:] == int(CtrlMode.ACTIVE)
    elif expect.mode is not None:
        hit = after & (modes == int(expect.mode))
    else:
        hit = after & ((faults >> expect.bit) & 1 == 1)
    at = int(since_ms[np.argmax(hit)]) if hit.any() else None
    return {"expect": expect.label(), "why": expect.why, "at_ms": at,
            "met": bool(at is not None and at <= expect.bound_ms)}


def _keep_ey(verdict: Verdict, result: Any, path: Any) -> None:
    """e_Y at the control instants (for the figure)."""
    from hil.metrics import path_errors

    plant = result.plant_trace
    at = np.round(plant["time"] * 1000).astype(int) % CONTROL_PERIOD_MS == 0
    pose = np.column_stack([plant["x"][at], plant["y"][at], plant["yaw"][at]])
    errors = path_errors(pose, path)
    verdict.time_s = [round(float(t), 3) for t in plant["time"][at]]
    verdict.e_y = [round(float(e), 5) for e in errors.lateral_error]
    last = plant["time"][at] >= plant["time"][at][-1] - SETTLE_WINDOW_S
    verdict.settled_abs_ey_m = float(np.mean(np.abs(errors.lateral_error[last])))


# --- running ------------------------------------------------------------------------------


class _EcuLogCounter(logging.Handler):
    """Counts what the ECU logs: caught exceptions and controller failures."""

    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.unexpected = 0
        self.controller = 0

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if "unexpected error" in text:
            self.unexpected += 1
        elif "controller step raised" in text:
            self.controller += 1


def c_not_applicable(case: FaultCase) -> str | None:
    """Why ``case`` cannot run against the C ECU (a separate process), or None when it can."""
    kinds = sorted({f.get("frame_kind") for f in case.table.get("bus", ())
                    if f.get("kind") == "lookalike"} & set(HUB_LOST_KINDS))
    if kinds:
        return (f"{' / '.join(kinds)} frames cannot reach a separate ECU process here: socketcand's "
                "raw-mode protocol, which the loopback hub speaks, has no FD, remote or error flag "
                "(python-can sends FD and error frames as classic data frames, which would be "
                "contract frames, and refuses a remote frame without data); the C ECU's receive "
                "path drops them by kind (tests/test_firmware_c_rx.py, the fuzz through libecu.so)")
    return None


def run_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
             duration_s: float | None = None, seed: int | None = None,
             source: object | None = None, ecu: str = "python") -> Verdict:
    """Run one case with one controller on a private virtual bus and judge it
    (``source`` names where the faults table came from in errors; default the case;
    ``ecu`` "c": the C executable on a loopback hub, as ``hil run --ecu c``)."""
    from hil.scenario import load_scenario
    from hil.session import SessionError, default_options, reference_path, run_hil
    from hil.time_master import TimeMasterError

    if ecu == "c" and (reason := c_not_applicable(case)) is not None:
        return Verdict(case.name, case.group, controller, f"{case.name}: {case.note}",
                       outcome="n/a", ecu=ecu, not_applicable=reason)
    if case.ecu_fault is not None:
        if ecu == "c":
            return run_c_ecu_case(case, controller, scenario_name, duration_s)
        return run_ecu_case(case, controller, scenario_name, duration_s)
    scenario = load_scenario(scenario_name)
    table = dict(case.table)
    if seed is not None:
        table["seed"] = seed
    spec = FaultSpec.from_mapping(table, source if source is not None else f"case {case.name!r}")
    changes: dict[str, Any] = {"faults": types.MappingProxyType(table)}
    if duration_s is not None:
        changes["duration_s"] = duration_s
    scenario = dataclasses.replace(scenario, **changes)
    description = "; ".join(f.describe() for f in spec.bus) or case.note or "no fault"
    if spec.bus and case.name != "cli":
        description = f"{case.name}: {description}"
    if case.group == "vehicle" and case.note and case.table:
        description = f"{case.name} ({case.note})"
    elif case.group == "vehicle":
        description = case.name if case.table else "no fault (baseline)"
    counter = _EcuLogCounter()
    logger = logging.getLogger("firmware_sim")
    logger.addHandler(counter)
    result, error = None, None
    try:
        result = run_hil(scenario, default_options(controller, faults=spec, ecu=ecu))
    except (TimeMasterError, SessionError) as e:
        # The ECU died or stopped ACKing: a crash is a result here, not the end. Anything
        # else is a fault of the harness and propagates.
        error = e
    finally:
        logger.removeHandler(counter)
    verdict = evaluate(case, controller, result, error, counter.unexpected, counter.controller,
                       description, reference_path(scenario))
    verdict.ecu = ecu
    return verdict


class _LogLines(logging.Handler):
    """Keeps what the ECU logs at WARNING and above (the lost bus's rate limit)."""

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


@dataclass
class _LostBusProbe:
    """The lost-bus case's wall-clock measurements (`_lose_bus`; `_lose_c_bus` for the C
    ECU, whose CPU time is its process's and whose receive calls are not counted: None)."""

    noticed_ms: float | None = None
    cpu_fraction: float = math.nan
    lost_wall_s: float = 0.0
    log_lines: int = 0
    lost_lines: int = 0
    reopen_tries: int = 0
    recv_calls: int | None = 0
    reopened_ms: float | None = None

    def expects(self) -> list[dict[str, Any]]:
        """The contract's rules for a lost bus as judged rows (bounds: wall clock)."""
        wall = self.lost_wall_s
        return [
            {"expect": "lost bus noticed <= 300 ms", "why": "receive errors for 100 ms are a "
             "lost bus (+ thread scheduling on a busy machine)",
             "at_ms": None if self.noticed_ms is None else round(self.noticed_ms),
             "met": self.noticed_ms is not None and self.noticed_ms <= 300},
            {"expect": "ECU thread CPU < 20 % while lost", "why": "not a busy loop",
             "at_ms": None, "shown": f"{100 * self.cpu_fraction:.1f} %" + (
                 "" if self.recv_calls is None else f", {self.recv_calls} receive calls"),
             "met": self.cpu_fraction < 0.2},
            {"expect": "lost-bus log lines <= 1/s", "why": "logged at most once a second",
             "at_ms": None, "shown": f"{self.lost_lines} of {self.log_lines} lines in {wall:.1f} s",
             "met": 1 <= self.lost_lines <= wall + 1 and self.log_lines <= 3 * (wall + 1)},
            {"expect": "reopen tried every 1 s", "why": "tries to reopen the bus every second",
             "at_ms": None, "shown": f"{self.reopen_tries} tries in {wall:.1f} s",
             "met": 1 <= self.reopen_tries <= wall + 1},
            {"expect": "reopened <= 1500 ms after the bus is back", "why": "next reopening "
             "within 1 s", "at_ms": None if self.reopened_ms is None else round(self.reopened_ms),
             "met": self.reopened_ms is not None and self.reopened_ms <= 1500},
        ]


def _lose_bus(ecu: Any, thread: threading.Thread, bus: Any, outage_s: float,
              back: threading.Event, reopen_tries: list[float]) -> _LostBusProbe:
    """Take ``bus`` away for ``outage_s`` of wall clock and watch the ECU meanwhile: when
    it notices, its thread's CPU time from then on (a busy loop shows as ~100 %), its log
    lines and reopening tries; then let the bus come back (``back``) and wait for the ECU
    to reopen it."""
    probe = _LostBusProbe()
    lines = _LogLines()
    logger = logging.getLogger("firmware_sim")
    logger.addHandler(lines)
    cpu_clock = time.pthread_getcpuclockid(thread.ident)
    started = time.monotonic()
    bus.lose()
    cpu_from = wall_from = None
    try:
        while time.monotonic() - started < outage_s:
            if cpu_from is None and ecu.bus_lost:
                wall_from = time.monotonic()
                cpu_from = time.clock_gettime(cpu_clock)
                probe.noticed_ms = 1000 * (wall_from - started)
            time.sleep(0.005)
        if cpu_from is not None:
            probe.lost_wall_s = time.monotonic() - wall_from
            probe.cpu_fraction = (time.clock_gettime(cpu_clock) - cpu_from) / probe.lost_wall_s
        probe.log_lines = len(lines.lines)
        probe.lost_lines = sum("bus lost" in line or "still lost" in line for line in lines.lines)
        probe.reopen_tries = len(reopen_tries)
        probe.recv_calls = bus.calls_while_lost
    finally:
        logger.removeHandler(lines)
    back.set()
    back_at = time.monotonic()
    while time.monotonic() - back_at < 3.0 and not ecu.bus_reopened:
        time.sleep(0.005)
    if ecu.bus_reopened:
        probe.reopened_ms = 1000 * (time.monotonic() - back_at)
    return probe


def run_ecu_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
                 duration_s: float | None = None) -> Verdict:
    """Run a fault of the time base or of the ECU's own bus (``case.ecu_fault``): the same
    nodes as ``hil.session.run_hil`` in lockstep on a private virtual bus, with the ECU in
    a thread here so that its bus (`LosableBus`) or the master's (`TimeShiftingBus`) can
    be wrapped; judged as `evaluate` judges every run, plus the case's own measurements."""
    from firmware_sim.ecu import Ecu
    from hil.bus import BusConfig, open_bus, private_virtual_channel
    from hil.faults import BusDownError, LosableBus, TimeShiftingBus
    from hil.planner_node import PlannerNode
    from hil.plant_node import PlantNode
    from hil.recorder import EcuFrameMonitor
    from hil.scenario import load_scenario
    from hil.session import HilRunResult, control_instant_metrics, reference_path
    from hil.time_master import LockstepMaster, TimeMasterError

    fault = case.ecu_fault
    assert fault is not None
    scenario = load_scenario(scenario_name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    onset_ms = round(fault["start_s"] * 1000)
    config = BusConfig("virtual", private_virtual_channel("faults"))
    back = threading.Event()
    reopen_tries: list[float] = []
    opened: list[Any] = []

    def reopen() -> Any:
        reopen_tries.append(time.monotonic())
        if not back.is_set():
            raise BusDownError("CAN interface still down")
        opened.append(open_bus(config))
        return opened[-1]

    counter = _EcuLogCounter()
    logging.getLogger("firmware_sim").addHandler(counter)
    ecu_bus = LosableBus(open_bus(config))
    master_bus: Any = open_bus(config)
    if fault["kind"] == "time_jump":
        master_bus = TimeShiftingBus(master_bus, onset_ms, fault["ahead_ms"])
    ecu = Ecu(ecu_bus, controller, {scenario.path_id: scenario.path_file}, lockstep=True,
              reopen_bus=reopen)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,), name="ecu-fault-case", daemon=True)
    plant, planner, monitor = PlantNode(scenario), PlannerNode(scenario), EcuFrameMonitor()
    master = LockstepMaster(master_bus, [plant, planner, monitor], ack_timeout_s=5.0,
                            peer_alive=lambda: None if thread.is_alive() else "ECU thread ended")
    probe, error, result = None, None, None
    started = time.monotonic()
    thread.start()
    try:
        master.handshake()
        for tick_ms in range(0, round(scenario.duration_s * 1000), 5):
            if fault["kind"] == "lost_bus" and tick_ms == onset_ms:
                probe = _lose_bus(ecu, thread, ecu_bus, fault["outage_s"], back, reopen_tries)
            master.tick(tick_ms)
    except TimeMasterError as e:   # the ECU stalled or died: a result of the case
        error = e
    finally:
        stop.set()
        thread.join(5.0)
        ecu.close()
        logging.getLogger("firmware_sim").removeHandler(counter)
        master_bus.shutdown()   # the ECU shut down its own bus (the reopened one too)
    if error is None:
        plant_trace = plant.trace()
        result = HilRunResult(
            scenario=scenario.name, controller=controller, bus=config.describe(),
            mode="lockstep", plant_trace=plant_trace, ecu_trace=monitor.trace(),
            tracking=control_instant_metrics(plant_trace, reference_path(scenario)),
            stats=master.stats, wall_time_s=time.monotonic() - started,
            extra={"ecu_frames_raw": monitor.raw})
    frames_hit = master_bus.record.actions if fault["kind"] == "time_jump" else 1
    verdict = evaluate(case, controller, result, error, counter.unexpected, counter.controller,
                       f"{case.name}: {case.note}", reference_path(scenario), onset_ms=onset_ms,
                       frames_hit=frames_hit)
    if fault["kind"] == "time_jump":
        verdict.expects.append(_jump_tasks_expect(monitor.raw, onset_ms))
    elif probe is not None:
        verdict.expects.extend(probe.expects())
    return verdict


def _jump_tasks_expect(raw: Sequence[tuple[int, int, bytes]], onset_ms: int) -> dict[str, Any]:
    """The time jump's own row: at most one control task at the jump TICK."""
    tasks = sum(1 for tick, frame_id, _ in raw
                if tick == onset_ms and frame_id == FrameId.STEER_TORQUE_CMD)
    return {"expect": "<= 1 control task at the jump TICK", "why": "the skipped tasks are not run",
            "at_ms": None, "shown": f"{tasks} task(s)", "met": tasks <= 1}


class _DroppingRelay:
    """A TCP relay between the C ECU and its hub that can take the ECU's bus away: `lose`
    closes the ECU's connection and, until `back`, accepts and at once closes every new
    one (counted: the ECU's reopening tries), as an interface that went down would."""

    def __init__(self, target_port: int) -> None:
        self._target = target_port
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(0.05)
        self.port = self._server.getsockname()[1]
        self._down = threading.Event()
        self._closed = threading.Event()
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self.refused = 0
        threading.Thread(target=self._accept, name="relay", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._server.accept()
            except (TimeoutError, OSError):
                continue
            if self._down.is_set():
                self.refused += 1
                client.close()
                continue
            upstream = socket.create_connection(("127.0.0.1", self._target))
            for sock in (client, upstream):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._sockets += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), name="relay-pump", daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (source, sink):
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def lose(self) -> None:
        """The bus goes away: the ECU's stream ends, new connections are refused."""
        self._down.set()
        with self._lock:
            sockets, self._sockets = self._sockets, []
        for sock in sockets:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def back(self) -> None:
        self._down.clear()

    def close(self) -> None:
        self._closed.set()
        self.lose()
        self._server.close()


def _process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process ``pid`` so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _lose_c_bus(ecu: Any, relay: _DroppingRelay, outage_s: float) -> _LostBusProbe:
    """`_lose_bus` for the C ECU process: its bus taken away at the relay for ``outage_s``
    of wall clock, watched through its output (when it says the bus is lost, its log lines,
    when it says it reopened) and its process CPU time; its reopening tries are the
    connections the relay refused."""
    probe = _LostBusProbe(recv_calls=None)
    output = Path(ecu.output_path)
    offset = len(output.read_bytes())

    def said() -> str:
        return output.read_bytes()[offset:].decode(errors="replace")

    started = time.monotonic()
    relay.lose()
    cpu_from = wall_from = None
    while time.monotonic() - started < outage_s:
        if cpu_from is None and "bus lost" in said():
            wall_from = time.monotonic()
            cpu_from = _process_cpu_s(ecu.process.pid)
            probe.noticed_ms = 1000 * (wall_from - started)
        time.sleep(0.005)
    if cpu_from is not None:
        probe.lost_wall_s = time.monotonic() - wall_from
        probe.cpu_fraction = (_process_cpu_s(ecu.process.pid) - cpu_from) / probe.lost_wall_s
    lines = said().splitlines()
    probe.log_lines = len(lines)
    probe.lost_lines = sum("bus lost" in line or "still lost" in line for line in lines)
    probe.reopen_tries = relay.refused
    relay.back()
    back_at = time.monotonic()
    while time.monotonic() - back_at < 3.0 and "bus reopened" not in said():
        time.sleep(0.005)
    if "bus reopened" in said():
        probe.reopened_ms = 1000 * (time.monotonic() - back_at)
    return probe


def run_c_ecu_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
                   duration_s: float | None = None) -> Verdict:
    """A fault of the time base or of the ECU's own bus against the C ECU: the executable on
    a loopback socketcand hub of its own (as ``hil.session.run_hil`` starts it for ``--ecu
    c``); the time master's bus wrapped in `TimeShiftingBus` (time jump), or the ECU's
    connection through a `_DroppingRelay` (lost bus); judged as `run_ecu_case` judges the
    Python ECU's run, the lost bus by the same rules from the process's output and CPU time."""
    from hil.bus import BusConfig, open_bus
    from hil.faults import TimeShiftingBus
    from hil.planner_node import PlannerNode
    from hil.plant_node import PlantNode
    from hil.recorder import EcuFrameMonitor
    from hil.scenario import load_scenario
    from hil.session import (HUB_CHANNEL, EcuProcess, HilRunResult, SessionError, c_ecu_command,
                             control_instant_metrics, default_options, reference_path)
    from hil.time_master import LockstepMaster, TimeMasterError
    from hil.timing.hub import LOOPBACK, READY_DELAY_S, LoopbackCanHub

    fault = case.ecu_fault
    assert fault is not None and fault["kind"] in ("time_jump", "lost_bus")
    scenario = load_scenario(scenario_name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    onset_ms = round(fault["start_s"] * 1000)
    options = default_options(controller, ecu="c")
    hub = LoopbackCanHub(port=0).start()
    relay = _DroppingRelay(hub.port) if fault["kind"] == "lost_bus" else None
    ecu: Any = None
    master_bus: Any = None
    probe, error, result = None, None, None
    started = time.monotonic()
    try:
        master_bus = open_bus(BusConfig("socketcand", HUB_CHANNEL), host=LOOPBACK, port=hub.port, tcp_tune=True)
        if fault["kind"] == "time_jump":
            master_bus = TimeShiftingBus(master_bus, onset_ms, fault["ahead_ms"])
        ecu = EcuProcess(scenario, options, c_ecu_command(scenario, options, relay.port if relay else hub.port))
        time.sleep(2 * READY_DELAY_S)   # the hub delivers to a new client after READY_DELAY_S
        plant, planner, monitor = PlantNode(scenario), PlannerNode(scenario), EcuFrameMonitor()
        master = LockstepMaster(master_bus, [plant, planner, monitor], ack_timeout_s=options.ack_timeout_s,
                                handshake_timeout_s=options.handshake_timeout_s,
                                peer_alive=ecu.alive_problem)
        master.handshake()
        for tick_ms in range(0, round(scenario.duration_s * 1000), 5):
            if relay is not None and tick_ms == onset_ms:
                probe = _lose_c_bus(ecu, relay, fault["outage_s"])
                time.sleep(2 * READY_DELAY_S)   # the reopened connection is a new client of the hub
            master.tick(tick_ms)
        plant_trace = plant.trace()
        result = HilRunResult(
            scenario=scenario.name, controller=controller, bus=f"socketcand:{HUB_CHANNEL} (loopback hub)",
            mode="lockstep", plant_trace=plant_trace, ecu_trace=monitor.trace(),
            tracking=control_instant_metrics(plant_trace, reference_path(scenario)),
            stats=master.stats, wall_time_s=time.monotonic() - started,
            extra={"ecu_frames_raw": monitor.raw, "ecu": "c"})
    except (TimeMasterError, SessionError) as e:   # the ECU stalled or died: a result of the case
        error = e
    finally:
        try:
            if ecu is not None:
                ecu.stop()
        finally:
            if master_bus is not None:
                master_bus.shutdown()
            if relay is not None:
                relay.close()
            hub.close()
    frames_hit = master_bus.record.actions if fault["kind"] == "time_jump" and master_bus is not None else 1
    verdict = evaluate(case, controller, result, error, 0, 0, f"{case.name}: {case.note}",
                       reference_path(scenario), onset_ms=onset_ms, frames_hit=frames_hit)
    verdict.ecu = "c"
    if result is not None and fault["kind"] == "time_jump":
        verdict.expects.append(_jump_tasks_expect(result.extra["ecu_frames_raw"], onset_ms))
    elif probe is not None:
        verdict.expects.extend(probe.expects())
    return verdict


@dataclass(frozen=True)
class FaultTask:
    """One (case, controller) run for a worker (picklable); ``index`` keeps the report's order."""

    key: str
    index: int
    case: FaultCase
    controller: str
    duration_s: float | None
    ecu: str = "python"


def run_fault_task(task: FaultTask) -> Verdict:
    """The executors' task: :func:`run_case` (a harness error propagates as the task's error)."""
    return run_case(task.case, task.controller, duration_s=task.duration_s, ecu=task.ecu)


def run_campaign(cases: Sequence[FaultCase], controllers: Sequence[str] | None = None,
                 duration_s: float | None = None,
                 executor_options: dict[str, Any] | None = None, ecu: str = "python") -> list[Verdict]:
    """Every (case, controller) run, verdicts in case order, with a tqdm progress bar.

    The runs are tasks of the campaigns' executors (``studies.campaign.executors``; default
    this process, ``executor_options`` e.g. ``{"workers": 2}`` for a local Ray or
    ``{"address": ...}`` for a cluster). The cases that measure the ECU's own wall-clock
    behaviour (:func:`ecu_cases`: a jump of virtual time, a lost bus) always run here,
    alone, after the others, so that no other run competes with them for the cores.
    ``ecu`` "c": every run against the C executable (a case it cannot take comes back as
    not applicable, `c_not_applicable`).
    """
    from tqdm import tqdm

    from studies.campaign.executors import open_executor

    jobs = [FaultTask(f"{case.name} / {c}", i, case, c, duration_s, ecu)
            for i, (case, c) in enumerate((case, c) for case in cases for c in case.controllers
                                          if controllers is None or c in controllers)]
    parallel = [job for job in jobs if job.case.ecu_fault is None]
    alone = [job for job in jobs if job.case.ecu_fault is not None]
    options = dict(executor_options or {"serial": True})
    verdicts: dict[int, Verdict] = {}
    with tqdm(total=len(jobs), desc="make faults", unit="run") as progress:
        for group, executor_kwargs in ((parallel, options), (alone, {"serial": True})):
            if not group:
                continue
            executor = open_executor(run_fault_task, **executor_kwargs)
            try:
                for job, verdict, worker_error in executor.run(group):
                    if worker_error is not None:
                        raise HilError(f"fault case {job.key}: the run failed in the harness: {worker_error}")
                    verdicts[job.index] = verdict
                    progress.set_postfix_str(job.key)
                    progress.update(1)
            finally:
                executor.close()
    return [verdicts[job.index] for job in jobs]


# --- report ------------------------------------------------------------------------------


def _ms(value: int | None) -> str:
    return "-" if value is None else f"{value}"


def markdown(verdicts: Sequence[Verdict], wall_s: float, command: str, ecu: str = "python",
             python_verdicts: Sequence[dict[str, Any]] | None = None) -> str:
    """results/faults.md (``ecu`` "c": results/faults_c.md, with the comparison against the
    Python campaign's verdicts ``python_verdicts``, rows of results/faults.json)."""
    if ecu == "c":
        title = "# Fault injection campaign against the C ECU (`make faults-c`)"
        where = ("the C ECU executable (build/firmware/ecu) as a process on a socketcand hub of "
                 "its own on TCP loopback, as `hil run --ecu c` runs it; lockstep")
    else:
        title, where = "# Fault injection campaign (`make faults`)", "lockstep on python-can's virtual bus"
    lines = [title, "",
             f"Scenario `dlc_high_mu` (35 km/h, mu 0.85, 13.5 s), {where}; faults start at "
             f"{ONSET_S} s (first lane change, X ~ 29 m) unless "
             "said otherwise. Generated by `" + command + f"` in {wall_s / 60:.1f} min.", "",
             "Detect = first control cycle after the fault's first action with a mode other "
             "than ACTIVE or a new FAULTS bit (ms). Expected = the contract's reaction and its "
             "bound, and when it came (ms after the first action). Outcome: tracked = max |e_Y| "
             f"<= {PATH_TOLERANCE_M} m; safe stop = SAFE_STOP and standstill at the end. "
             "Invalid = commands with CMD_VALID = 1 that broke a limit (decoded with cantools "
             "from the DBC, CRC recomputed; |steer| <= 0.3 rad, |torque| <= 3000 N m, mode "
             "ACTIVE/DEGRADED/SAFE_STOP, no drive torque in SAFE_STOP).", "",
             "Contract revision 2 cases: implausible plant values with a valid CRC, CAN FD / "
             "extended-ID / remote / error look-alikes (\"no reaction\" = ACTIVE and none of "
             "FAULTS bits 0, 1, 3 newly set for the bound), replays, a jump of virtual time "
             "(HIL_SYNC 10 s ahead: the ECU's clock jumps, the plant's does not) and a lost "
             "bus (the ECU's interface down for 2.5 s of wall clock; lockstep stops meanwhile, "
             "so its bounds and figures are wall clock and vary from run to run).", ""]
    for group, title in (("bus", "Bus, frame-kind and time-base faults (ESO-DKMPC)"),
                         ("vehicle", "Vehicle faults (ESO-DKMPC against DKMPC)")):
        rows = [v for v in verdicts if v.group == group and not v.not_applicable]
        if not rows:
            continue
        vehicle = group == "vehicle"
        lines += [f"## {title}", "",
                  "| fault | controller | mode sequence | detect (ms) | expected (at ms) | "
                  "max \\|e_Y\\| (m) | " + ("\\|e_Y\\| last 2 s (m) | " if vehicle else "")
                  + "outcome | invalid / checked | crashes |",
                  "|---|---|---|---|---|---|---|---|---|" + ("---|" if vehicle else "")]
        for v in rows:
            expected = "; ".join(f"{e['expect']} ({e.get('shown', _ms(e['at_ms']))}) "
                                 f"{'ok' if e['met'] else 'MISSED'}" for e in v.expects) or "-"
            crash = str(v.crashes) + (f" ({v.crash_reason})" if v.crash_reason else "")
            settled = f"{v.settled_abs_ey_m:.3f} | " if vehicle else ""
            lines.append(f"| {v.description} | {v.controller} | {v.mode_sequence} | "
                         f"{_ms(v.detect_ms)} | {expected} | {v.max_abs_ey_m:.3f} | {settled}"
                         f"{v.outcome} | {v.invalid_commands} / {v.commands_checked} | {crash} |")
        lines.append("")
    skipped = [v for v in verdicts if v.not_applicable]
    if skipped:
        lines += ["## Not applicable to this ECU", "", "| fault | controller | why |", "|---|---|---|"]
        lines += [f"| {v.case} | {v.controller} | {v.not_applicable} |" for v in skipped]
        lines.append("")
    ran = [v for v in verdicts if not v.not_applicable]
    total_invalid = sum(v.invalid_commands for v in ran)
    total_crash = sum(v.crashes for v in ran)
    failed = [f"{v.case} / {v.controller}" for v in ran if not v.passed()]
    lines += ["## Summary", "",
              f"- runs: {len(ran)}" + (f" (+ {len(skipped)} not applicable)" if skipped else "")
              + f"; crashes: {total_crash}; invalid commands: "
              f"{total_invalid} of {sum(v.commands_checked for v in ran)} checked",
              f"- expectations met: {sum(e['met'] for v in ran for e in v.expects)} of "
              f"{sum(len(v.expects) for v in ran)}",
              f"- controller exceptions turned into the guarded fallback: "
              f"{sum(v.controller_errors for v in ran)}" + (" (the C ECU's QP fallback shows as "
                                                             "FAULTS bit 2; it has no exceptions)"
                                                             if ecu == "c" else ""),
              f"- runs not meeting every criterion: {', '.join(failed) if failed else 'none'}", ""]
    if python_verdicts is not None:
        lines += comparison(verdicts, python_verdicts)
    return "\n".join(lines)


def _expects_summary(expects: Sequence[dict[str, Any]]) -> str:
    return f"{sum(e['met'] for e in expects)}/{len(expects)}"


def comparison(verdicts: Sequence[Verdict], python_verdicts: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: each run's verdict beside the Python campaign's for the same case and
    controller (``python_verdicts``: rows of results/faults.json): outcome, expectations met,
    detect time, max |e_Y| and the mode sequence; a row is marked where they differ."""
    theirs = {(row["case"], row["controller"]): row for row in python_verdicts}
    lines = ["## Against the Python ECU's campaign (results/faults.json)", "",
             "Same cases, controllers and judge; \"same\" = the same outcome, the same "
             "expectations met, the same detect time and mode sequence.", "",
             "| fault | controller | outcome C / Python | expectations met C / Python | "
             "detect (ms) C / Python | max \\|e_Y\\| (m) C / Python | verdict |",
             "|---|---|---|---|---|---|---|"]
    counts = {"same": 0, "differs": 0, "no Python row": 0, "n/a": 0}
    for v in verdicts:
        row = theirs.get((v.case, v.controller))
        if v.not_applicable:
            counts["n/a"] += 1
            continue
        if row is None:
            counts["no Python row"] += 1
            lines.append(f"| {v.case} | {v.controller} | {v.outcome} / - | - | - | - | no Python row |")
            continue
        met = [e["met"] for e in v.expects]
        same = (v.outcome == row["outcome"] and met == [e["met"] for e in row["expects"]]
                and v.detect_ms == row["detect_ms"] and v.mode_sequence == row["mode_sequence"])
        verdict = "same" if same else ("same outcome" if v.passed() == row["passed"] and
                                       v.outcome == row["outcome"] else "DIFFERS")
        counts["same" if same else "differs"] += 1
        lines.append(f"| {v.case} | {v.controller} | {v.outcome} / {row['outcome']} | "
                     f"{_expects_summary(v.expects)} / {_expects_summary(row['expects'])} | "
                     f"{_ms(v.detect_ms)} / {_ms(row['detect_ms'])} | "
                     f"{v.max_abs_ey_m:.3f} / {row['max_abs_ey_m']:.3f} | {verdict} |")
    lines += ["", f"- identical verdicts: {counts['same']}; differing in some figure: "
              f"{counts['differs']}; without a Python row: {counts['no Python row']}; "
              f"not applicable here: {counts['n/a']}", ""]
    return lines


def figure(verdicts: Sequence[Verdict], path: Path, scenario_name: str = SCENARIO) -> Path:
    """e_Y over time for the vehicle faults, ESO-DKMPC against DKMPC: one panel per fault,
    one line per controller (its legend gives the max |e_Y|)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(v.case for v in verdicts if v.group == "vehicle"))
    if not cases:
        return path
    fig, axes = plt.subplots(len(cases), 1, figsize=(8, 1.9 * len(cases) + 0.8), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, case in zip(axes, cases):
        for v in verdicts:
            if v.case == case and v.e_y:
                ax.plot(v.time_s, v.e_y, label=f"{v.controller} (max |e_Y| {v.max_abs_ey_m:.2f} m)")
        ax.axhline(0.0, color="0.6", linewidth=0.6, label="reference path (e_Y = 0)")
        ax.set_title("no fault (baseline)" if case == "none" else f"fault: {case}", fontsize=9)
        ax.set_ylabel("e_Y (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"Vehicle faults in {scenario_name} (35 km/h, mu 0.85, lockstep HIL)\n"
                 "lateral error e_Y of the true pose to the reference path: ESO-DKMPC "
                 "against DKMPC", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def check_paths(out_dir: Path, replace: bool, scenario_name: str = SCENARIO, ecu: str = "python") -> None:
    """Refuse an unusable output folder before any run: its parent missing, a file, not
    writable, holding an earlier campaign's results (without ``replace``) or where an
    input of the campaign (scenario, its path file, the DBC) would be overwritten.

    Raises:
        hil.errors.OutputPathError, hil.errors.ScenarioError, can_defs.errors.DbcLoadError.
    """
    from can_defs.codec import prepare
    from can_defs.dbc import DBC_PATH
    from hil.output_paths import check_output_folder
    from hil.scenario import load_scenario

    prepare()
    scenario = load_scenario(scenario_name)
    inputs = [Path(scenario.source), Path(scenario.path_file), DBC_PATH]
    check_output_folder(out_dir, "--out", result_files(ecu), replace=replace, inputs=inputs)


def python_verdicts(out_dir: Path) -> list[dict[str, Any]] | None:
    """The Python campaign's verdicts in ``out_dir`` (faults.json), None when there are none.

    Raises:
        HilError: the file is there but not the campaign's JSON.
    """
    path = out_dir / RESULT_FILES[1]
    if not path.is_file():
        return None
    try:
        rows = json.loads(path.read_text(encoding="utf-8"))
        if not all(isinstance(r, dict) and {"case", "controller", "outcome", "expects"} <= r.keys() for r in rows):
            raise ValueError("a row without case / controller / outcome / expects")
    except (ValueError, TypeError) as e:
        raise HilError(f"{path}: not the fault campaign's verdicts: {e}") from e
    return rows


def write_results(verdicts: Sequence[Verdict], out_dir: Path, wall_s: float, command: str,
                  ecu: str = "python") -> list[Path]:
    """results/faults.md, faults.json and faults_vehicle.png (``ecu`` "c": faults_c.*,
    compared with the Python campaign's faults.json in ``out_dir`` when it is there;
    ``out_dir`` checked by `check_paths`; created when missing, its parent never)."""
    md_name, json_name, png_name = result_files(ecu)
    reference = python_verdicts(out_dir) if ecu != "python" else None
    out_dir.mkdir(exist_ok=True)
    md = out_dir / md_name
    md.write_text(markdown(verdicts, wall_s, command, ecu, reference), encoding="utf-8")
    js = out_dir / json_name
    rows = []
    for v in verdicts:
        row = dataclasses.asdict(v)
        row.pop("e_y")
        row.pop("time_s")
        row["passed"] = v.passed()
        rows.append(row)
    js.write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")
    png = figure(verdicts, out_dir / png_name)
    return [md, js, png]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.fault_campaign [--out results] [--only NAME ...]``; exit 1 when a run
    crashed, sent an invalid command, left the path without a safe stop or missed a bound."""
    from can_defs.errors import CanDefsError

    parser = argparse.ArgumentParser(prog="python -m studies.fault_campaign", description=__doc__.split("\n")[0])
    add_arguments(parser)
    try:
        return run_from_args(parser.parse_args(argv))
    except (HilError, CanDefsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the campaign (``python -m hil faults --campaign`` has the same ones)."""
    from studies.campaign.executors import add_executor_arguments

    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite the results of an earlier campaign in --out")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME",
                        help="run only these cases (names as in the table)")
    parser.add_argument("--controllers", nargs="+", default=None,
                        help="restrict to these controllers")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="shorten the scenario (s); default the full 13.5 s")
    parser.add_argument("--ecu", choices=ECUS, default="python",
                        help="the Python ECU (results faults.*) or the C executable build/firmware/ecu "
                             "(results faults_c.*, compared with faults.*); default python")
    add_executor_arguments(parser, default_workers="none: without --workers or --address the runs "
                                                   "go to this process")


def executor_options(args: argparse.Namespace) -> dict[str, Any]:
    """Where the runs go: ``--serial`` or neither ``--workers`` nor ``--address``: this
    process; else Ray (local with ``--workers`` CPUs, or the cluster at ``--address``)."""
    address, workers = getattr(args, "address", None), getattr(args, "workers", None)
    if getattr(args, "serial", False) or (address is None and workers is None):
        if address is not None:
            raise HilError("--serial and --address exclude each other")
        return {"serial": True}
    return {"address": address, "workers": workers}


def run_from_args(args: argparse.Namespace) -> int:
    """Run the campaign as ``args`` say, write the results, print the summary."""
    cases = all_cases()
    if args.only:
        known = {c.name for c in cases}
        unknown = [n for n in args.only if n not in known]
        if unknown:
            raise HilError(f"unknown case(s) {unknown}; known: {sorted(known)}")
        cases = [c for c in cases if c.name in args.only]
    if args.duration is not None and not args.duration > 0:
        raise HilError(f"--duration must be > 0 s, got {args.duration}")
    ecu = getattr(args, "ecu", "python")   # `hil faults --campaign` has no --ecu
    if ecu == "c":
        from hil.session import check_c_ecu, default_options

        for controller in {c for case in cases for c in case.controllers}:
            if args.controllers is None or controller in args.controllers:
                check_c_ecu(default_options(controller, ecu="c"))
    check_paths(args.out, args.replace, ecu=ecu)
    started = time.monotonic()
    verdicts = run_campaign(cases, args.controllers, args.duration, executor_options(args), ecu)
    wall = time.monotonic() - started
    target = "make faults" + ("-c" if ecu == "c" else "")
    command = target if not (args.only or args.controllers or args.duration) \
        else ("python -m hil faults --campaign " if ecu == "python"
              else "python -m studies.fault_campaign ") + " ".join(
            f"--{k} {v if not isinstance(v, list) else ' '.join(map(str, v))}"
            for k, v in (("ecu", ecu if ecu != "python" else None), ("only", args.only),
                         ("controllers", args.controllers), ("duration", args.duration)) if v)
    for path in write_results(verdicts, args.out, wall, command, ecu):
        print(f"wrote {path}")
    ran = [v for v in verdicts if not v.not_applicable]
    bad = [v for v in ran if not v.passed()]
    print(f"{len(ran)} runs ({len(verdicts) - len(ran)} not applicable), "
          f"{sum(v.crashes for v in ran)} crashes, "
          f"{sum(v.invalid_commands for v in ran)} invalid commands, "
          f"{len(bad)} not meeting every criterion")
    return 1 if any(v.crashes or v.invalid_commands for v in ran) else 0


if __name__ == "__main__":
    sys.exit(main())

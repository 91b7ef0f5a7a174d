"""The fault campaign's case catalogue (``make faults``, ``studies.fault_campaign``): the
campaign's scenario and fault onset, the contract's expected reactions (`Expect` and their
bounds), `FaultCase`, the injector's cases (`campaign_cases`, also the campaign grid's
fault catalogue), the ECU-level ones (`ecu_cases`: a jump of virtual time, a lost bus) and
the input files' (`input_cases`).

Bus faults run with ESO-DKMPC; vehicle faults with ESO-DKMPC and DKMPC (the observer is
what should make them survivable). Faults start at 3.0 s, in the first lane change
(X ~ 29 m).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from can_defs.frames import HANDSHAKE_TICK, CtrlMode
from hil.fault_cases.input_cases import CONTROLLER as INPUT_CONTROLLER, INPUT_CASES
from hil.faults import PLANNER_IDS, PLANT_IDS

#: Where the fault starts in the campaign (s): mid first lane change of the DLC.
ONSET_S = 3.0
#: The campaign's scenario.
SCENARIO = "dlc_high_mu"


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


# Contract bounds (docs/can-contract.md, fault reaction), counted from the first frame the
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
# Rev. 2, a failing controller: fallbacks (FAULTS bit 2) on 4 control tasks in a row, the
# first at t0 and the last at t0 + 75 ms, make the task at t0 + 100 ms SAFE_STOP; one task
# of margin (the input-file case "model A x 1e6", hil.fault_cases.input_runs).
CONTROLLER_FAILED_BOUND_MS = 125
# Lockstep: a lost bus stops virtual time (no tick arrives), so once the bus is back the
# run goes on with no reaction in virtual time.
LOCKSTEP_PAUSE = Expect(500, "lockstep: no tick while the bus is lost, no input timeout",
                        quiet=True)
# A replay of 1 s whose counters read as next is accepted once its positions are
# continuous; when the real frames return 1 s later their position is not continuous with
# the replayed one for 100 ms, so the next is a restarted reference (lost): SAFE_STOP.
REPLAY_END = Expect(1000 + 115, "real frames back: no continuous sample for 100 ms",
                    mode=CtrlMode.SAFE_STOP)


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
    #: ``{"kind": "lost_bus", "start_s", "outage_s"}``; a bad input file
    #: (``{"kind": "input", ...}``: ``hil.fault_cases.input_cases``); None: the injector's
    #: ``table``.
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


def input_cases() -> list[FaultCase]:
    """A bad input file given to the ECU at start-up (``hil.fault_cases.input_cases``: the
    files and the verdict each case expects of both ECUs), with its controller."""
    return [FaultCase(case.name, "bus", {}, (INPUT_CONTROLLER,), (), case.note, ecu_fault=case.ecu_fault())
            for case in INPUT_CASES]


def all_cases() -> list[FaultCase]:
    """Every case of `make faults`: the injector's (`campaign_cases`, also the campaign
    grid's fault catalogue), the ECU-level ones (`ecu_cases`) and the input files'
    (`input_cases`)."""
    return campaign_cases() + ecu_cases() + input_cases()

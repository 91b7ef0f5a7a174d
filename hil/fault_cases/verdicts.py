"""The fault campaign's judge: what one run showed, from the frames alone (`Verdict`).

Per run (`evaluate`):

- the ECU's mode sequence and FAULTS bits, from its STEER_TORQUE_CMD / CTRL_DIAG frames;
- time to detect: first control cycle at or after the fault's first action (the tick at
  which the injector first changed a frame; t = 0 for vehicle faults) with a mode other
  than ACTIVE or a FAULTS bit that was clear in the cycle before the onset;
- each expected reaction of the contract (``Expect``: a mode or a FAULTS bit) and whether it
  came within its bound;
- max |e_Y| of the true pose (t = 0, 25, 50, ... ms) and the outcome: ``safe stop`` (SAFE_STOP
  and the plant at standstill at the end; SAFE_STOP steers straight, so it may leave the
  path), else ``tracked`` (max |e_Y| <= 1 m), else ``FAILED``; the input-file cases
  (``hil.fault_cases.input_runs``) have two outcomes of their own, set only where the case
  expects them and every row is met: ``refused to start`` and ``FAULT latched``;
- invalid commands, checked independently of the ECU's own code: every ECU frame decoded
  with cantools from the DBC, CRC recomputed; a STEER_TORQUE_CMD with CMD_VALID = 1 is
  invalid when its CRC is wrong, |steer| > 0.3 rad, |torque| > the ECU's 3000 N m (inside
  the DBC's range), its CTRL_MODE is not ACTIVE / DEGRADED / SAFE_STOP, or it drives
  (torque > 0) in SAFE_STOP;
- crashes: the run raised (ECU thread died, ACK timeout) or the ECU logged an
  "unexpected error" (an exception its RX / control path caught).

The ECU-level cases add rows of their own: the lost bus's wall-clock measurements
(`LostBusProbe`) and the time jump's control tasks (`jump_tasks_expect`).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from can_defs.frames import CtrlMode, FrameId
from hil.fault_cases.catalogue import Expect, FaultCase

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
#: Bus bits whose new appearance counts as a reaction (bit 2 is the solver's fallback).
REACTION_BITS = 0b1011
#: Outcomes of a run that passes: the vehicle kept on the path or safely stopped, or (input-
#: file cases only, where the case expects it) the ECU refused its bad file at start-up or
#: latched FAULT for it, commanding nothing.
PASSING_OUTCOMES = ("tracked", "safe stop", "refused to start", "FAULT latched")


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
        """No crash, no invalid command, a passing outcome (`PASSING_OUTCOMES`),
        expectations met (False for a case that did not run: ``not_applicable``)."""
        return (not self.not_applicable and self.crashes == 0 and self.invalid_commands == 0
                and self.outcome in PASSING_OUTCOMES and self.expects_met)


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


@dataclass
class LostBusProbe:
    """The lost-bus case's wall-clock measurements (``hil.fault_cases.python_ecu._lose_bus``;
    ``hil.fault_cases.c_ecu._lose_c_bus`` for the C ECU, whose CPU time is its process's and
    whose receive calls are not counted: None)."""

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


def jump_tasks_expect(raw: Sequence[tuple[int, int, bytes]], onset_ms: int) -> dict[str, Any]:
    """The time jump's own row: at most one control task at the jump TICK."""
    tasks = sum(1 for tick, frame_id, _ in raw
                if tick == onset_ms and frame_id == FrameId.STEER_TORQUE_CMD)
    return {"expect": "<= 1 control task at the jump TICK", "why": "the skipped tasks are not run",
            "at_ms": None, "shown": f"{tasks} task(s)", "met": tasks <= 1}

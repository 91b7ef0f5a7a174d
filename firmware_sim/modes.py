"""The ECU mode state machine as a pure function: ``transition(mode, events) -> (mode, reasons)``.

Rules (``docs/can-contract.md``, "Modes and fault reaction"), evaluated once per control task,
one transition per evaluation:

- FAULT is latched: nothing leaves it; a failed model or path load enters it from any mode.
- INIT -> STANDBY once the first consistent plant sample has arrived.
- STANDBY -> ACTIVE when ENGAGE = 1, the PATH_ID is loaded, PLANNER_REQ is on time, the
  plant sample is fresh and, after a SAFE_STOP, ENGAGE has been 0 in between (``rearmed``).
- ACTIVE / DEGRADED -> SAFE_STOP when no good sample for > 100 ms, or when the controller
  fell back (FAULTS bit 2) on the last 4 control tasks in a row (rev. 2: a failing
  controller); either wins over the planner's reasons (SAFE_STOP is not left by ENGAGE = 0
  while moving either); otherwise
  -> STANDBY on ENGAGE = 0, an unknown PATH_ID or a PLANNER_REQ timeout; otherwise
  -> DEGRADED when the sample is older than 20 ms, -> ACTIVE when it is fresh again.
- SAFE_STOP -> STANDBY only at standstill and on ENGAGE = 0, an unknown PATH_ID or a
  PLANNER_REQ timeout; fresh samples alone never leave SAFE_STOP.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

from can_defs.frames import CtrlMode

#: Modes in which STEER_TORQUE_CMD carries CMD_VALID = 1 (contract).
VALID_COMMAND_MODES = frozenset({CtrlMode.ACTIVE, CtrlMode.DEGRADED, CtrlMode.SAFE_STOP})


class Reason(enum.Enum):
    """Why a transition was taken (for logs and tests)."""

    LOAD_FAILED = "model or path failed to load"
    FIRST_SAMPLE = "first consistent plant sample"
    ENGAGED = "ENGAGE = 1 with a known PATH_ID and fresh inputs"
    DISENGAGED = "ENGAGE = 0"
    UNKNOWN_PATH = "unknown PATH_ID"
    PLANNER_TIMEOUT = "PLANNER_REQ missing > 100 ms"
    SAMPLE_STALE = "plant sample older than 20 ms"
    SAMPLE_LOST = "no good plant sample for > 100 ms"
    CONTROLLER_FAILED = "solver fallback on 4 control tasks in a row"
    SAMPLE_RECOVERED = "fresh plant sample again"
    STANDSTILL = "vehicle stands still"


@dataclass(frozen=True)
class ModeEvents:
    """The conditions the state machine looks at, evaluated at one control task.

    Attributes:
        load_failed: the model or a reference path failed to load.
        sample_seen: at least one consistent plant sample arrived since start.
        sample_fresh: the newest good sample is at most 20 ms old.
        sample_lost: no good sample for more than 100 ms (or none at all).
        planner_ok: a PLANNER_REQ arrived within the last 100 ms.
        engage: ENGAGE of the newest PLANNER_REQ.
        path_known: PATH_ID of the newest PLANNER_REQ is loaded.
        rearmed: ENGAGE has been 0 since the last SAFE_STOP (True when none happened).
        standstill: a fresh sample shows |vx| below the standstill speed.
        controller_failed: the controller's step fell back (FAULTS bit 2) on the last
            ``EcuConfig.controller_failed_cycles`` control tasks in a row (rev. 2).
    """

    load_failed: bool = False
    sample_seen: bool = True
    sample_fresh: bool = True
    sample_lost: bool = False
    planner_ok: bool = True
    engage: bool = True
    path_known: bool = True
    rearmed: bool = True
    standstill: bool = False
    controller_failed: bool = False


def _disengage_reasons(events: ModeEvents) -> tuple[Reason, ...]:
    """Planner-side reasons to return to STANDBY (empty when the request stands)."""
    reasons: list[Reason] = []
    if not events.planner_ok:
        reasons.append(Reason.PLANNER_TIMEOUT)
    else:
        if not events.engage:
            reasons.append(Reason.DISENGAGED)
        if not events.path_known:
            reasons.append(Reason.UNKNOWN_PATH)
    return tuple(reasons)


def transition(mode: CtrlMode, events: ModeEvents) -> tuple[CtrlMode, tuple[Reason, ...]]:
    """Next mode and the reasons for it; ``reasons`` is empty when the mode is kept."""
    if mode is CtrlMode.FAULT:
        return mode, ()
    if events.load_failed:
        return CtrlMode.FAULT, (Reason.LOAD_FAILED,)
    if mode is CtrlMode.INIT:
        if events.sample_seen:
            return CtrlMode.STANDBY, (Reason.FIRST_SAMPLE,)
        return mode, ()
    disengage = _disengage_reasons(events)
    if mode is CtrlMode.STANDBY:
        if not disengage and events.rearmed and events.sample_fresh:
            return CtrlMode.ACTIVE, (Reason.ENGAGED,)
        return mode, ()
    if mode is CtrlMode.SAFE_STOP:
        if disengage and events.standstill:
            return CtrlMode.STANDBY, disengage + (Reason.STANDSTILL,)
        return mode, ()
    # ACTIVE or DEGRADED. A lost sample or a failing controller goes first: SAFE_STOP is
    # not left on ENGAGE = 0 while moving, so disengaging must not bypass it when both
    # happen in one cycle (STANDBY would leave the plant holding the failed steer, coasting).
    stop = ((Reason.SAMPLE_LOST,) if events.sample_lost else ()) + \
        ((Reason.CONTROLLER_FAILED,) if events.controller_failed else ())
    if stop:
        return CtrlMode.SAFE_STOP, stop
    if disengage:
        return CtrlMode.STANDBY, disengage
    if not events.sample_fresh:
        if mode is CtrlMode.DEGRADED:
            return mode, ()
        return CtrlMode.DEGRADED, (Reason.SAMPLE_STALE,)
    if mode is CtrlMode.DEGRADED:
        return CtrlMode.ACTIVE, (Reason.SAMPLE_RECOVERED,)
    return mode, ()

"""Exhaustive table test of the ECU mode state machine (firmware_sim.modes.transition)."""
from __future__ import annotations

import dataclasses
import itertools

from can_defs.frames import CtrlMode

from firmware_sim.modes import VALID_COMMAND_MODES, ModeEvents, Reason, transition

EVENT_FIELDS = [f.name for f in dataclasses.fields(ModeEvents)]


def all_events() -> list[ModeEvents]:
    """Every combination of the boolean events (2**10)."""
    return [ModeEvents(**dict(zip(EVENT_FIELDS, values)))
            for values in itertools.product((False, True), repeat=len(EVENT_FIELDS))]


def contract_oracle(mode: CtrlMode, e: ModeEvents) -> CtrlMode:
    """The contract's "Fault reaction of the ECU", sentence by sentence."""
    if mode is CtrlMode.FAULT or e.load_failed:       # load failure: FAULT, latched
        return CtrlMode.FAULT
    if mode is CtrlMode.INIT:                           # INIT until the first consistent sample
        return CtrlMode.STANDBY if e.sample_seen else CtrlMode.INIT
    request_stands = e.planner_ok and e.engage and e.path_known
    if mode is CtrlMode.STANDBY:                        # ENGAGE=1, known path, fresh inputs
        ok = request_stands and e.sample_fresh and e.rearmed
        return CtrlMode.ACTIVE if ok else CtrlMode.STANDBY
    if mode is CtrlMode.SAFE_STOP:                      # left only through STANDBY at standstill
        return CtrlMode.STANDBY if (not request_stands and e.standstill) else CtrlMode.SAFE_STOP
    if e.sample_lost or e.controller_failed:            # > 100 ms without a good sample, or
        return CtrlMode.SAFE_STOP                       # 4 fallbacks in a row (rev. 2); both
                                                        # dominate disengaging
    if not request_stands:                              # ENGAGE=0 / unknown path / timeout
        return CtrlMode.STANDBY
    return CtrlMode.ACTIVE if e.sample_fresh else CtrlMode.DEGRADED


def test_transition_matches_contract_table_for_every_mode_and_event_combination():
    checked = 0
    for mode in CtrlMode:
        for events in all_events():
            new_mode, reasons = transition(mode, events)
            assert new_mode is contract_oracle(mode, events), (mode, events)
            # reasons are given exactly when the mode changes
            assert bool(reasons) == (new_mode is not mode), (mode, events, reasons)
            assert all(isinstance(reason, Reason) for reason in reasons)
            checked += 1
    print(f"checked {checked} (mode, events) combinations")
    assert checked == len(CtrlMode) * 2 ** len(EVENT_FIELDS) == 6144


def test_safe_stop_never_returns_directly_to_control():
    targets = {transition(CtrlMode.SAFE_STOP, events)[0] for events in all_events()}
    print("SAFE_STOP can go to:", sorted(m.name for m in targets))
    assert targets == {CtrlMode.SAFE_STOP, CtrlMode.STANDBY, CtrlMode.FAULT}


def test_fault_is_latched_and_entered_from_every_mode():
    for events in all_events():
        assert transition(CtrlMode.FAULT, events)[0] is CtrlMode.FAULT
    for mode in CtrlMode:
        assert transition(mode, ModeEvents(load_failed=True))[0] is CtrlMode.FAULT


def test_active_is_only_reached_from_standby_or_degraded():
    sources = {mode for mode in CtrlMode for events in all_events()
               if mode is not CtrlMode.ACTIVE and transition(mode, events)[0] is CtrlMode.ACTIVE}
    print("modes that can enter ACTIVE:", sorted(m.name for m in sources))
    assert sources == {CtrlMode.STANDBY, CtrlMode.DEGRADED}


def test_named_transitions_give_their_reasons():
    assert transition(CtrlMode.INIT, ModeEvents(sample_seen=True)) == (CtrlMode.STANDBY, (Reason.FIRST_SAMPLE,))
    assert transition(CtrlMode.STANDBY, ModeEvents()) == (CtrlMode.ACTIVE, (Reason.ENGAGED,))
    assert transition(CtrlMode.ACTIVE, ModeEvents(sample_fresh=False)) == (CtrlMode.DEGRADED, (Reason.SAMPLE_STALE,))
    assert transition(CtrlMode.DEGRADED, ModeEvents(sample_fresh=False, sample_lost=True)) == \
        (CtrlMode.SAFE_STOP, (Reason.SAMPLE_LOST,))
    assert transition(CtrlMode.DEGRADED, ModeEvents()) == (CtrlMode.ACTIVE, (Reason.SAMPLE_RECOVERED,))
    assert transition(CtrlMode.ACTIVE, ModeEvents(path_known=False)) == (CtrlMode.STANDBY, (Reason.UNKNOWN_PATH,))
    assert transition(CtrlMode.ACTIVE, ModeEvents(planner_ok=False)) == (CtrlMode.STANDBY, (Reason.PLANNER_TIMEOUT,))
    # both inputs gone in one cycle: the safe reaction, not a silent CMD_VALID = 0
    assert transition(CtrlMode.DEGRADED, ModeEvents(planner_ok=False, sample_fresh=False, sample_lost=True)) == \
        (CtrlMode.SAFE_STOP, (Reason.SAMPLE_LOST,))
    assert transition(CtrlMode.SAFE_STOP, ModeEvents(engage=False, standstill=True)) == \
        (CtrlMode.STANDBY, (Reason.DISENGAGED, Reason.STANDSTILL))
    # moving, or still engaged: stays in SAFE_STOP
    assert transition(CtrlMode.SAFE_STOP, ModeEvents(engage=False))[0] is CtrlMode.SAFE_STOP
    assert transition(CtrlMode.SAFE_STOP, ModeEvents(standstill=True))[0] is CtrlMode.SAFE_STOP
    # after a SAFE_STOP, ENGAGE must have been 0 before ACTIVE again
    assert transition(CtrlMode.STANDBY, ModeEvents(rearmed=False))[0] is CtrlMode.STANDBY


def test_a_failing_controller_leaves_active_and_degraded_for_safe_stop():
    """Rev. 2: a fallback on 4 control tasks in a row is a failing controller; it stops the
    vehicle from ACTIVE and DEGRADED even when the planner disengages in the same cycle.
    From STANDBY and SAFE_STOP the event changes nothing (no law runs there)."""
    failed = ModeEvents(controller_failed=True)
    for mode in (CtrlMode.ACTIVE, CtrlMode.DEGRADED):
        assert transition(mode, failed) == (CtrlMode.SAFE_STOP, (Reason.CONTROLLER_FAILED,))
        assert transition(mode, ModeEvents(controller_failed=True, engage=False, sample_fresh=False)) == \
            (CtrlMode.SAFE_STOP, (Reason.CONTROLLER_FAILED,))
    assert transition(CtrlMode.ACTIVE, ModeEvents(controller_failed=True, sample_lost=True)) == \
        (CtrlMode.SAFE_STOP, (Reason.SAMPLE_LOST, Reason.CONTROLLER_FAILED))
    assert transition(CtrlMode.SAFE_STOP, failed)[0] is CtrlMode.SAFE_STOP
    assert transition(CtrlMode.STANDBY, failed)[0] is CtrlMode.ACTIVE


def test_valid_command_modes_are_the_contracts():
    assert VALID_COMMAND_MODES == {CtrlMode.ACTIVE, CtrlMode.DEGRADED, CtrlMode.SAFE_STOP}

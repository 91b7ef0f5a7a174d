"""The fault campaign's input-file cases (``hil.fault_cases.input_cases``, run by
``hil.fault_cases.input_runs``): each case once against the Python ECU and, where the C
ECU is built (``make firmware``), against the C ECU, with the same judged verdict; and the
judge failing an ECU that takes the file."""
from __future__ import annotations

import math
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hil.fault_cases import input_cases
from hil.fault_cases.catalogue import FaultCase, all_cases
from hil.fault_cases.c_ecu import c_not_applicable
from hil.fault_cases.runs import run_case
from hil.fault_cases.verdicts import Verdict
from hil.run_types import C_ECU_EXECUTABLE
from studies.fault_report import markdown

NAMES = [case.name for case in input_cases.INPUT_CASES]
OUTCOMES = {"excitation chirp 1e308": "refused to start", "model with an infinite encoder weight": "FAULT latched",
            "path line over 4096 bytes": "FAULT latched", "path line with a NUL byte": "FAULT latched",
            "model A x 1e6": "safe stop"}


def case_named(name: str) -> FaultCase:
    return next(case for case in all_cases() if case.name == name)


def judged(verdict: Verdict) -> tuple:
    """What both ECUs must share (the FAULT line's wording is each ECU's own)."""
    return (verdict.outcome, verdict.mode_sequence, verdict.detect_ms,
            [(e["expect"], e["met"]) for e in verdict.expects])


def run_short(name: str, ecu: str) -> Verdict:
    """The case in 1 s of dlc_smoke; a failing controller's in the whole 4 s, in which its
    safe stop brakes to standstill (3.8 s)."""
    case = case_named(name)
    duration_s = None if case.ecu_fault["expect"] == "safe_stop" else 1.0
    verdict = run_case(case, input_cases.CONTROLLER, "dlc_smoke", duration_s=duration_s, ecu=ecu)
    print(f"\n{name} ({ecu}): {verdict.outcome}; "
          f"{[(e['expect'], e.get('shown'), e['met']) for e in verdict.expects]}")
    return verdict


@pytest.mark.parametrize("name", NAMES)
def test_an_input_case_gets_one_verdict_from_both_ecus(name: str) -> None:
    python = run_short(name, "python")
    assert python.passed() and python.outcome == OUTCOMES[name], python.expects
    assert python.crashes == 0 and python.invalid_commands == 0
    if python.outcome == "FAULT latched":
        assert python.mode_sequence == "FAULT" and python.commands_checked == 0
    if not C_ECU_EXECUTABLE.is_file():
        pytest.skip("the C ECU is not built (make firmware)")
    c = run_short(name, "c")
    assert c.ecu == "c" and c.passed(), c.expects
    assert judged(c) == judged(python)


def test_the_input_cases_are_in_the_campaign_for_both_ecus() -> None:
    """Registered in the catalogue, run against the C ECU too, and listed in the report."""
    cases = [case_named(name) for name in NAMES]
    assert len(cases) == 5 and all(c_not_applicable(case) is None for case in cases)
    verdict = Verdict(NAMES[0], "bus", input_cases.CONTROLLER, "d", outcome="refused to start",
                      expects=[{"expect": "e", "why": "w", "at_ms": None, "met": True}])
    assert f"| d | {input_cases.CONTROLLER} | " in markdown([verdict], "make faults")


@pytest.mark.parametrize("name, good", [
    ("excitation chirp 1e308", lambda folder, path, ecu: input_cases.BadInput(path, excite="prbs-torque")),
    ("path line over 4096 bytes", lambda folder, path, ecu: input_cases.BadInput(path, path_file=path)),
    ("model A x 1e6", lambda folder, path, ecu: input_cases.BadInput(path)),   # the default model
])
def test_the_judge_fails_an_ecu_that_takes_the_file(monkeypatch, name: str, good) -> None:
    """A good file in place of the bad one: the ECU starts (or drives), so the case fails."""
    defect = case_named(name).ecu_fault["defect"]
    monkeypatch.setitem(input_cases.WRITERS, defect, good)
    verdict = run_short(name, "python")
    assert not verdict.passed() and verdict.outcome != OUTCOMES[name]
    assert not all(e["met"] for e in verdict.expects)


def test_a_failing_controller_is_stopped_within_the_bound_by_both_ecus() -> None:
    """The model A x 1e6 (every step falls back): SAFE_STOP 100 ms after the first fallback
    (the 4 tasks in a row, within the 125 ms bound), held to the end with the safe stop's
    command, at standstill, and not one command outside the limits, in both ECUs."""
    for ecu in ("python", "c"):
        if ecu == "c" and not C_ECU_EXECUTABLE.is_file():
            pytest.skip("the C ECU is not built (make firmware)")
        verdict = run_short("model A x 1e6", ecu)
        assert verdict.passed() and verdict.outcome == "safe stop", verdict.expects
        assert verdict.mode_sequence == "ACTIVE, SAFE_STOP@0.125"
        assert verdict.expects[0]["at_ms"] == 100
        assert verdict.invalid_commands == 0 and verdict.commands_checked > 100


def test_the_safe_stop_rows_fail_an_ecu_that_keeps_driving_on_a_failing_controller() -> None:
    """The rows of the failing-controller case on the trace of an ECU without the rule
    (ACTIVE to the end, every task a fallback, as both ECUs were before it) and of one that
    stops too late or steers back too fast."""
    from hil.fault_cases.input_runs import _safe_stop_rows

    def trace(modes: list[int], steer: list[float]) -> SimpleNamespace:
        n = len(modes)
        return SimpleNamespace(ecu_trace={
            "time": 0.025 * np.arange(n), "ctrl_mode": np.array(modes), "cmd_valid": np.ones(n),
            "steer_angle_cmd": np.array(steer), "drive_torque_cmd": np.where(np.array(modes) == 4, -1500.0, 0.0),
            "faults": np.where(np.array(modes) == 2, 4, 0)})

    def met(modes: list[int], steer: list[float]) -> list[bool]:
        return [row["met"] for row in _safe_stop_rows(trace(modes, steer))]

    assert met([1] + [2] * 4 + [4] * 5, [0.1] * 5 + [0.095, 0.09, 0.085, 0.08, 0.075]) == [True] * 3
    assert met([1] + [2] * 9, [0.1] * 10) == [False, False, False]                  # no rule
    assert met([1] + [2] * 6 + [4] * 3, [0.1] * 7 + [0.095, 0.09, 0.085]) == [False, True, True]   # 150 ms
    assert met([1] + [2] * 4 + [4] * 5, [0.1] * 5 + [0.0] * 5) == [True, True, False]  # straight at once
    assert met([1] + [2] * 4 + [4, 4, 2, 4, 4], [0.1] * 10) == [True, False, True]     # ACTIVE again


def test_a_data_files_record_value_is_set_in_place() -> None:
    """``set_record_value`` on a file of two records: only the named record's first value."""
    def record(name: str, values: list[float]) -> bytes:
        return (name.encode().ljust(48, b"\0") + struct.pack("<5I", 1, len(values), 1, 1, 1)
                + struct.pack(f"<{len(values)}d", *values))

    data = b"ECUDATA1" + struct.pack("<I", 2) + record("ts", [0.025]) + record("koopman.w0", [1.0, 2.0])
    changed = input_cases.set_record_value(data, "koopman.w0", math.inf)
    assert changed == data.replace(struct.pack("<d", 1.0), struct.pack("<d", math.inf))
    with pytest.raises(ValueError, match="no record 'koopman.A'"):
        input_cases.set_record_value(data, "koopman.A", math.nan)
    with pytest.raises(ValueError, match="magic ECUDATA1 missing"):
        input_cases.set_record_value(b"PK" + data, "ts", 0.0)


def test_the_path_cases_spoil_line_3_only(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_bytes(b"x,y,yaw\n0,0,0\n0.25,0,0\n0.5,0,0\n")
    long = input_cases.write_bad_input("path line over 4096 bytes", tmp_path, path, "python")
    nul = input_cases.write_bad_input("path line with a NUL byte", tmp_path, path, "c")
    assert long.path_file.read_bytes() == b"x,y,yaw\n0,0,0\n0.25,0,0" + b" " * 4200 + b"\n0.5,0,0\n"
    assert nul.path_file.read_bytes() == b"x,y,yaw\n0,0,0\n0\x00.25,0,0\n0.5,0,0\n"

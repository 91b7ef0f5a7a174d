"""The fault campaign against the C ECU executable (``make faults-c``,
``python -m studies.fault_campaign --ecu c``): short runs of campaign cases against the C
ECU judged as the Python ECU's runs are, the cases it cannot take reported with a reason,
and the comparison with the Python campaign's verdicts."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from hil.fault_cases import c_ecu as fault_c_ecu, catalogue as fault_cases
from studies import fault_campaign, fault_report
from hil.fault_cases.catalogue import FaultCase
from hil.fault_cases.runs import run_case
from hil.fault_cases.verdicts import Verdict
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)


def short(name: str, start_s: float = 0.5) -> FaultCase:
    """A campaign case moved to ``start_s`` with LMPC (dlc_smoke runs of about a second)."""
    case = next(c for c in fault_cases.all_cases() if c.name == name)
    table = {**case.table, "bus": [{**b, "start_s": start_s} for b in case.table.get("bus", [])]}
    fault = None if case.ecu_fault is None else {**case.ecu_fault, "start_s": start_s}
    return dataclasses.replace(case, table=table, ecu_fault=fault, controllers=("lmpc",))


def judged(verdict: Verdict) -> tuple:
    return (verdict.mode_sequence, verdict.detect_ms, verdict.outcome,
            [(e["expect"], e["at_ms"], e["met"]) for e in verdict.expects])


@pytest.mark.parametrize("name", ["VX 327 m/s", "wrong_crc", "virtual time jump", "extended-ID look-alikes"])
def test_a_case_against_the_c_ecu_is_judged_as_against_the_python_ecu(native, name: str) -> None:
    """The same case, scenario and controller against both ECUs: the C run passes, with
    the Python run's mode sequence, detect time and expectations (the equivalence of the
    two ECUs' fault reactions, seen through the campaign's judge)."""
    case = short(name)
    python = run_case(case, "lmpc", "dlc_smoke", duration_s=1.5)
    c = run_case(case, "lmpc", "dlc_smoke", duration_s=1.5, ecu="c")
    print(f"\n{name}: C {judged(c)}")
    assert c.ecu == "c" and not c.not_applicable
    assert c.crashes == 0 and c.invalid_commands == 0 and c.commands_checked > 40, c.crash_reason
    assert c.passed() and python.passed()
    assert judged(c) == judged(python)


def test_the_c_ecus_lost_bus_is_judged_by_the_same_rules(native) -> None:
    """The ECU's connection dropped and refused at a relay for 2.5 s of wall clock: it
    says so once, does not spin, retries every second, reopens, and lockstep goes on with
    no reaction (the Python case's rows, from the process's output and CPU time)."""
    c = run_case(short("lost bus"), "lmpc", "dlc_smoke", duration_s=1.5, ecu="c")
    rows = {e["expect"]: e for e in c.expects}
    print(f"\nlost bus: C {[(e['expect'], e.get('shown', e['at_ms'])) for e in c.expects]}")
    assert c.passed() and c.mode_sequence == "ACTIVE"
    assert set(rows) >= {"lost bus noticed <= 300 ms", "ECU thread CPU < 20 % while lost",
                         "reopen tried every 1 s", "reopened <= 1500 ms after the bus is back"}
    assert rows["reopen tried every 1 s"]["shown"].startswith(("2 tries", "3 tries"))


@pytest.mark.parametrize("name, why", [
    ("CAN FD look-alikes", "fd frames cannot reach a separate ECU process"),
    ("remote and error frames", "error / remote frames cannot reach a separate ECU process"),
])
def test_cases_the_c_ecu_cannot_take_are_reported_with_the_reason(name: str, why: str) -> None:
    """Not run (no process started: nothing to build) and not dropped: a verdict that says
    why, outside the pass / fail counts."""
    case = next(c for c in fault_cases.all_cases() if c.name == name)
    verdict = run_case(case, "eso-dkmpc", ecu="c")
    assert verdict.outcome == "n/a" and why in verdict.not_applicable and not verdict.passed()
    text = fault_report.markdown([verdict], "make faults-c", "c")
    assert "## Not applicable to this ECU" in text and f"| {name} | eso-dkmpc | " in text
    assert "- runs: 0 (+ 1 not applicable)" in text


def test_every_other_case_is_run_against_the_c_ecu() -> None:
    runnable = [c.name for c in fault_cases.all_cases() if fault_c_ecu.c_not_applicable(c) is None]
    assert len(runnable) == len(fault_cases.all_cases()) - 2
    assert {"extended-ID look-alikes", "virtual time jump", "lost bus"} <= set(runnable)


def test_results_compare_each_verdict_with_the_python_campaigns(tmp_path: Path) -> None:
    """faults_c.* beside faults.json: one comparison row per run, "same" where outcome,
    expectations, detect time and mode sequence agree, "DIFFERS" where the outcome does."""
    expects = [{"expect": "bit 0 <= 35 ms", "why": "", "at_ms": 10, "met": True}]
    python = [Verdict("drop 5 %", "bus", "eso-dkmpc", "", "ACTIVE", 10, expects, 0.1, outcome="tracked"),
              Verdict("mass +200 kg", "vehicle", "dkmpc", "", "ACTIVE", None, [], 0.2, outcome="tracked")]
    rows = [{**dataclasses.asdict(v), "passed": v.passed()} for v in python]
    (tmp_path / "faults.json").write_text(json.dumps(rows))
    c = [dataclasses.replace(python[0], ecu="c"),
         dataclasses.replace(python[1], ecu="c", max_abs_ey_m=1.5, outcome="FAILED")]
    written = fault_report.write_results(c, tmp_path, 60.0, "make faults-c", "c")
    assert [p.name for p in written] == ["faults_c.md", "faults_c.json", "faults_c_vehicle.png",
                                         "faults_c_timing.json"]
    text = written[0].read_text()
    assert "## Against the Python ECU's campaign (results/faults.json)" in text
    assert "| drop 5 % | eso-dkmpc | tracked / tracked | 1/1 / 1/1 | 10 / 10 | 0.100 / 0.100 | same |" in text
    assert "| mass +200 kg | dkmpc | FAILED / tracked |" in text and text.count("DIFFERS") == 1
    assert "- identical verdicts: 1; differing in some figure: 1;" in text
    assert json.loads(written[1].read_text())[0]["ecu"] == "c"
    assert (tmp_path / "faults.json").read_text() == json.dumps(rows)   # the Python results untouched


def test_an_unbuilt_c_ecu_is_one_error_line_before_any_run(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr("hil.ecu_runners.C_ECU_EXECUTABLE", tmp_path / "no-ecu")  # where check_c_ecu reads it
    assert fault_campaign.main(["--ecu", "c", "--out", str(tmp_path / "out")]) == 1
    assert capsys.readouterr().err.strip() == (f"error: the C ECU {tmp_path / 'no-ecu'} is not built: "
                                               "run make firmware")
    assert not (tmp_path / "out").exists()

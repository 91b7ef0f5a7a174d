"""The fault campaign's committed report (studies/fault_report.py) holds what the verdicts
decide and nothing of the machine: the wall times go to a timing file under logs/."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.fault_cases.verdicts import Verdict
from studies import fault_report

EXPECTS = [{"expect": "bit 0 <= 35 ms", "why": "", "at_ms": 10, "met": True}]


@pytest.mark.parametrize("ecu", ["python", "c"])
def test_the_report_does_not_depend_on_the_wall_times(tmp_path: Path, ecu: str) -> None:
    """The same verdicts after a 1 min and a 30 min campaign (runs of 3 s and 40 s): the
    same faults.md and faults.json bytes; the wall times only in logs/faults*_timing.json."""
    written = {}
    for wall_s, run_s in ((60.0, 3.0), (1800.0, 40.0)):
        verdicts = [Verdict("drop 5 %", "bus", "eso-dkmpc", "d", "ACTIVE", 10, EXPECTS, 0.1, outcome="tracked",
                            wall_s=run_s, ecu=ecu)]
        out = tmp_path / f"{wall_s:.0f}"
        written[wall_s] = fault_report.write_results(verdicts, out, wall_s, f"make faults ({ecu})", ecu)
    (md, js, _, times), (md_long, js_long, _, times_long) = written[60.0], written[1800.0]
    assert md.read_bytes() == md_long.read_bytes() and js.read_bytes() == js_long.read_bytes()
    assert "wall_s" not in json.loads(js.read_text())[0]
    assert f"logs/{times.name} (not under version control)" in md.read_text()
    assert times.parent == md.parent / "logs" and times.name == fault_report.timing_file(ecu)
    timing = json.loads(times_long.read_text())
    assert timing["wall_s"] == 1800.0 and timing["runs"] == [{"case": "drop 5 %", "controller": "eso-dkmpc",
                                                              "wall_s": 40.0}]
    assert timing["command"] == f"make faults ({ecu})" and timing["machine"]

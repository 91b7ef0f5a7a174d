"""The fault campaign as grid files on the campaign engine (``studies/campaign/grids/
faults.toml``, ``faults_c.toml``; the ``fault_case`` runner): the grids load with every
(case, controller) of the catalogue, the wall-clock cases are exclusive, a small grid run
through the engine gives run_case's verdicts, and the fault report renders from its rows."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.fault_cases.catalogue import all_cases
from hil.fault_cases.runs import run_case
from studies import fault_report
from studies.campaign.__main__ import main as campaign_main
from studies.campaign.fault_case_cell import verdict_of_row
from studies.campaign.grid import FAULT_CASE_RUNNER, GridError, load_grid


def judged(verdict) -> tuple:
    return (verdict.case, verdict.controller, verdict.description, verdict.mode_sequence,
            verdict.detect_ms, verdict.outcome, verdict.invalid_commands, verdict.commands_checked,
            verdict.crashes, [(e["expect"], e["at_ms"], e["met"]) for e in verdict.expects],
            verdict.max_abs_ey_m, verdict.e_y)


@pytest.mark.parametrize("name, ecu", [("faults", "python"), ("faults_c", "c")])
def test_the_fault_grids_are_every_case_with_its_controllers(name: str, ecu: str) -> None:
    grid = load_grid(name)
    assert {cell.runner for cell in grid.cells} == {FAULT_CASE_RUNNER}
    assert {cell.ecu for cell in grid.cells} == {ecu}
    pairs = [(case.name, c) for case in all_cases() for c in case.controllers]
    assert sorted((cell.case, cell.controller) for cell in grid.cells) == sorted(pairs)
    exclusive = {cell.case for cell in grid.cells if cell.exclusive}
    assert exclusive == {case.name for case in all_cases() if case.ecu_fault is not None}
    assert {"virtual time jump", "lost bus"} <= exclusive
    assert grid.c_left_out == {}   # a case the C ECU cannot take is run and reported n/a


@pytest.mark.parametrize("extra, message", [
    ('mu = [0.5]', "axes.mu with runner 'fault_case'"),
    ('case = ["no such case"]', "not a case of the fault catalogue"),
    ('runner = ["fault_case", "hil"]', "stands alone"),
])
def test_fault_case_grids_are_checked_before_any_run(tmp_path: Path, extra: str, message: str) -> None:
    axes = {"runner": 'runner = "fault_case"', "controller": 'controller = ["eso-dkmpc"]',
            "scenario": 'scenario = "dlc_high_mu"'}
    key = extra.split(" ")[0]
    axes[key] = extra
    (tmp_path / "g.toml").write_text("[axes]\n" + "\n".join(axes.values()) + "\n")
    with pytest.raises(GridError, match=message):
        load_grid(tmp_path / "g.toml")


def test_a_case_axis_needs_the_fault_case_runner(tmp_path: Path) -> None:
    (tmp_path / "g.toml").write_text('[axes]\ncontroller = "lmpc"\nscenario = "dlc_smoke"\ncase = ["drop 5 %"]\n')
    with pytest.raises(GridError, match="needs runner"):
        load_grid(tmp_path / "g.toml")


def test_a_small_fault_grid_on_the_engine_gives_run_cases_verdicts(tmp_path: Path) -> None:
    """Two cases (one exclusive), one controller, through ``python -m studies.campaign``:
    the same verdicts as run_case directly, the exclusive case last, nothing cached, and
    ``python -m studies.fault_report`` renders the rows as the campaign's report."""
    grid_file = tmp_path / "faults_small.toml"
    grid_file.write_text('name = "faults_small"\n[axes]\nrunner = "fault_case"\n'
                         'controller = ["eso-dkmpc"]\nscenario = "dlc_high_mu"\n'
                         'case = ["virtual time jump", "drop 5 %"]\n[run]\nduration_s = 4.0\n')
    assert [c.exclusive for c in load_grid(grid_file).cells] == [True, False]
    out = tmp_path / "campaign"
    assert campaign_main([str(grid_file), "--out", str(out), "--serial", "--no-progress"]) == 0
    rows = json.loads((out / "rows.json").read_text())
    assert [row["case"] for row in rows] == ["virtual time jump", "drop 5 %"]   # grid order
    assert not any((out / "cache").iterdir())                                  # never cached
    import csv
    with (out / "cells.csv").open() as handle:
        assert [(r["fault"], r["end_reason"]) for r in csv.DictReader(handle)] == \
            [(row["case"], row["outcome"]) for row in rows]                    # the case in the fault column
    cases = {case.name: case for case in all_cases()}
    for row in rows:
        direct = run_case(cases[row["case"]], "eso-dkmpc", duration_s=4.0)
        assert judged(verdict_of_row(row)) == judged(direct)
        assert row["completed"] == int(direct.passed()) and row["end_reason"] == direct.outcome
    report = tmp_path / "report"
    assert fault_report.main([str(grid_file), "--campaign", str(out), "--out", str(report)]) == 0
    text = (report / "faults.md").read_text()
    assert text.index("| drop 5 %: ") < text.index("| virtual time jump: ")   # the catalogue's order
    written = json.loads((report / "faults.json").read_text())
    assert [(r["case"], r["passed"]) for r in written] == [(v.case, v.passed()) for v in
                                                            fault_report.verdicts_from_rows(rows)]


def test_exclusive_cells_run_last_alone_after_the_executor_is_released(tmp_path: Path, monkeypatch) -> None:
    from studies.campaign.executors import SerialExecutor
    from studies.campaign.runner import run_campaign

    grid_file = tmp_path / "g.toml"
    grid_file.write_text('[axes]\nrunner = "fault_case"\ncontroller = ["eso-dkmpc"]\nscenario = "dlc_high_mu"\n'
                         'case = ["lost bus", "drop 5 %", "virtual time jump", "delay"]\n')
    ran: list[tuple[str, bool]] = []

    class Recording(SerialExecutor):
        closed = False

        def close(self) -> None:
            Recording.closed = True

    def task(job):
        ran.append((job.case, Recording.closed))
        return {"key": job.key, "completed": 1}

    # the exclusive cells run the grid's own cell task, here the recording one
    monkeypatch.setattr("studies.campaign.runner.cell_task", lambda grid: task)

    result = run_campaign(load_grid(grid_file), tmp_path / "out", Recording(task), progress=False)
    assert ran == [("drop 5 %", False), ("delay", False), ("lost bus", True), ("virtual time jump", True)]
    assert [row["case"] for row in result.rows] == ["lost bus", "drop 5 %", "virtual time jump", "delay"]
    again = run_campaign(load_grid(grid_file), tmp_path / "out", SerialExecutor(task), progress=False)
    assert again.cached == 0 and again.computed == 4   # fault cells are never cached

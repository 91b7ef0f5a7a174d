"""The fault campaign's runs on the campaign engine: the cases of the catalogue as the
``fault_case`` cells of the grid ``faults`` (``faults_c`` for the C ECU;
``studies/campaign/grids/``), run by ``studies.campaign.runner.run_campaign`` on the
campaigns' executors, each cell one ``hil.fault_cases.runs.run_case`` (`run_campaign`).
"""
from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hil.errors import HilError
from hil.fault_cases.catalogue import FaultCase
from hil.fault_cases.verdicts import Verdict

#: The grid of each ECU's campaign (``make faults``, ``make faults-c``).
GRIDS = {"python": "faults", "c": "faults_c"}


def fault_grid(cases: Sequence[FaultCase], controllers: Sequence[str] | None = None,
               duration_s: float | None = None, ecu: str = "python") -> Any:
    """The ECU's fault grid (:data:`GRIDS`) with only the cells of ``cases`` (cases of the
    catalogue) and ``controllers`` (None: every one a case names), shortened to
    ``duration_s`` (None: the scenario's).

    Raises:
        HilError: a case that is not the catalogue's.
    """
    from studies.campaign.fault_axes import fault_cases
    from studies.campaign.grid import load_grid

    catalogue = fault_cases()
    for case in cases:
        if catalogue.get(case.name) != case:
            raise HilError(f"fault case {case.name!r}: not a case of the fault catalogue as it stands "
                           "(the campaign runs the catalogue's cases by name)")
    grid = load_grid(GRIDS[ecu])
    names = {case.name for case in cases}
    cells = tuple(cell for cell in grid.cells if cell.case in names
                  and (controllers is None or cell.controller in controllers))
    return dataclasses.replace(grid, cells=cells, duration_s=duration_s)


def run_campaign(cases: Sequence[FaultCase], controllers: Sequence[str] | None = None,
                 duration_s: float | None = None,
                 executor_options: dict[str, Any] | None = None, ecu: str = "python") -> list[Verdict]:
    """Every (case, controller) run, verdicts in case order, with a tqdm progress bar.

    The runs are the cells of :func:`fault_grid` on the campaign engine, on the campaigns'
    executors (``studies.campaign.executors``; default this process, ``executor_options``
    e.g. ``{"workers": 2}`` for a local Ray or ``{"address": ...}`` for a cluster). The
    cases that measure the ECU's own wall-clock behaviour (an ECU-level fault: a jump of
    virtual time, a lost bus, a bad input file) are exclusive cells: they run here, alone,
    after the others, so that no other run competes with them for the cores. ``ecu`` "c":
    every run against the C executable (a case it cannot take comes back as not
    applicable, ``hil.fault_cases.c_ecu.c_not_applicable``). No cell is cached (their
    verdicts hold wall-clock measurements).

    Raises:
        HilError: a run failed in the harness (the verdicts of the others are lost).
        KeyboardInterrupt: interrupted.
    """
    from studies.campaign.executors import open_executor
    from studies.campaign.fault_case_cell import run_fault_case_cell
    from studies.campaign.runner import run_campaign as run_grid
    from studies.fault_report import verdicts_from_rows

    grid = fault_grid(cases, controllers, duration_s, ecu)
    executor = open_executor(run_fault_case_cell, **dict(executor_options or {"serial": True}))
    try:
        with tempfile.TemporaryDirectory(prefix="fault-campaign-") as folder:
            result = run_grid(grid, Path(folder), executor)
    finally:
        executor.close()
    if result.interrupted:
        raise KeyboardInterrupt
    for row in result.rows:
        if row.get("error"):
            raise HilError(f"fault case {row['case']} / {row['controller']}: the run failed in the "
                           f"harness: {row['error']}")
    order = {case.name: i for i, case in enumerate(cases)}
    return verdicts_from_rows(result.rows, order)

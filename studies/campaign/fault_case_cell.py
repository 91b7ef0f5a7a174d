"""A campaign cell on the ``fault_case`` runner: one case of the fault catalogue with one
controller, run and judged by ``hil.fault_cases.runs.run_case`` (what ``make faults`` runs
for each (case, controller); the grids ``faults`` and ``faults_c``), against the Python ECU
or the C ECU executable (the ``ecu`` axis). The grid's rules for this runner are
``studies.campaign.fault_axes``'.

:func:`run_fault_case_cell` is the executors' task (a Ray worker, or this process): it
takes a :class:`FaultCaseJob` (plain data) and never raises for a failure of the run: the
error is in the row (``error``, ``end_reason`` "error"), as a scenario cell's.

Row fields: every field of the case's ``hil.fault_cases.verdicts.Verdict`` (``case``,
``group``, ``description``, ``mode_sequence``, ``detect_ms``, ``expects``, ...; the e_Y
trace ``e_y`` / ``time_s`` included, for the report's figure) and ``passed``; for
``cells.csv`` and ``summary.md``: ``completed`` (1 when the verdict passed), ``end_reason``
(the outcome: ``tracked``, ``safe stop``, ``FAILED``, ``n/a``, ...), ``e_y_max`` (max
|e_Y|), ``e_y_rmse`` (over the trace), ``heading_rmse`` (not judged: NaN), ``error``.
:func:`verdict_of_row` gives the Verdict back (``studies.fault_report`` renders from it).

Exclusive cells: the cases that measure the ECU's own wall-clock behaviour (an ECU-level
fault: a jump of virtual time, a lost bus, a bad input file; ``FaultCase.ecu_fault``) run
alone, in the driver, after every other cell (``Cell.exclusive``; the campaign runner
honours it), so that no other run competes with them for the cores.

Not cached: a verdict holds wall-clock measurements (the lost bus's reaction times and CPU
share, each run's wall time) that differ from run to run, and the campaign is a check of
the ECU as it is now, so every ``fault_case`` cell runs each time (``cacheable`` False).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
import traceback
from dataclasses import dataclass
from typing import Any

from studies.campaign.fault_axes import fault_cases


@dataclass(frozen=True)
class FaultCaseJob:
    """What a worker needs for one fault case cell: the case's name, the controller, the
    shipped scenario, the shortened duration (None: the scenario's), the ECU; ``exclusive``
    and ``cacheable`` for the campaign runner."""

    key: str
    case: str
    controller: str
    scenario: str
    duration_s: float | None = None
    ecu: str = "python"
    exclusive: bool = False
    cacheable: bool = False


def case_is_exclusive(name: str) -> bool:
    """The case measures the ECU's own wall-clock behaviour (an ECU-level fault)."""
    return fault_cases()[name].ecu_fault is not None


def fault_case_job(grid: Any, cell: Any) -> FaultCaseJob:
    """The worker's job for a ``fault_case`` cell of ``grid``; its key names the cell (the
    rows' key; never a cache entry)."""
    material = json.dumps({"cell": cell.as_dict(), "duration_s": grid.duration_s}, sort_keys=True)
    key = hashlib.sha256(material.encode()).hexdigest()[:24]
    return FaultCaseJob(key=key, case=cell.case, controller=cell.controller, scenario=cell.scenario,
                        duration_s=grid.duration_s, ecu=cell.ecu, exclusive=cell.exclusive)


def run_fault_case_cell(job: FaultCaseJob) -> dict[str, Any]:
    """Run and judge one case (see the module docstring for the row)."""
    from hil.fault_cases.runs import run_case

    started = time.perf_counter()
    try:
        verdict = run_case(fault_cases()[job.case], job.controller, job.scenario,
                           duration_s=job.duration_s, ecu=job.ecu)
    except Exception as e:  # noqa: BLE001 - recorded in the row: a failure of the harness
        return {"key": job.key, "case": job.case, "controller": job.controller, "ecu": job.ecu,
                "completed": 0, "end_reason": "error", "error": f"{type(e).__name__}: {e}",
                "traceback": traceback.format_exc(limit=8), "wall_s": time.perf_counter() - started}
    row: dict[str, Any] = {"key": job.key, **dataclasses.asdict(verdict)}
    e_y = [abs(v) for v in verdict.e_y]
    row.update(passed=verdict.passed(), completed=int(verdict.passed()), end_reason=verdict.outcome,
               e_y_max=verdict.max_abs_ey_m, heading_rmse=math.nan, error="",
               e_y_rmse=math.sqrt(sum(v * v for v in e_y) / len(e_y)) if e_y else math.nan)
    return row


def verdict_of_row(row: dict[str, Any]) -> Any:
    """The ``Verdict`` a ``fault_case`` cell's row holds."""
    from hil.fault_cases.verdicts import Verdict

    return Verdict(**{f.name: row[f.name] for f in dataclasses.fields(Verdict)})

"""The fault campaign's runs: every (case, controller) run of the campaign as tasks of the
campaigns' executors (`run_campaign`), each one ``hil.fault_cases.runs.run_case``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from hil.errors import HilError
from hil.fault_cases.catalogue import FaultCase
from hil.fault_cases.runs import run_case
from hil.fault_cases.verdicts import Verdict


@dataclass(frozen=True)
class FaultTask:
    """One (case, controller) run for a worker (picklable); ``index`` keeps the report's order."""

    key: str
    index: int
    case: FaultCase
    controller: str
    duration_s: float | None
    ecu: str = "python"


def run_fault_task(task: FaultTask) -> Verdict:
    """The executors' task: :func:`run_case` (a harness error propagates as the task's error)."""
    return run_case(task.case, task.controller, duration_s=task.duration_s, ecu=task.ecu)


def run_campaign(cases: Sequence[FaultCase], controllers: Sequence[str] | None = None,
                 duration_s: float | None = None,
                 executor_options: dict[str, Any] | None = None, ecu: str = "python") -> list[Verdict]:
    """Every (case, controller) run, verdicts in case order, with a tqdm progress bar.

    The runs are tasks of the campaigns' executors (``studies.campaign.executors``; default
    this process, ``executor_options`` e.g. ``{"workers": 2}`` for a local Ray or
    ``{"address": ...}`` for a cluster). The cases that measure the ECU's own wall-clock
    behaviour (:func:`ecu_cases`: a jump of virtual time, a lost bus) always run here,
    alone, after the others, so that no other run competes with them for the cores.
    ``ecu`` "c": every run against the C executable (a case it cannot take comes back as
    not applicable, `c_not_applicable`).
    """
    from tqdm import tqdm

    from studies.campaign.executors import open_executor

    jobs = [FaultTask(f"{case.name} / {c}", i, case, c, duration_s, ecu)
            for i, (case, c) in enumerate((case, c) for case in cases for c in case.controllers
                                          if controllers is None or c in controllers)]
    parallel = [job for job in jobs if job.case.ecu_fault is None]
    alone = [job for job in jobs if job.case.ecu_fault is not None]
    options = dict(executor_options or {"serial": True})
    verdicts: dict[int, Verdict] = {}
    with tqdm(total=len(jobs), desc="make faults", unit="run") as progress:
        for group, executor_kwargs in ((parallel, options), (alone, {"serial": True})):
            if not group:
                continue
            executor = open_executor(run_fault_task, **executor_kwargs)
            try:
                for job, verdict, worker_error in executor.run(group):
                    if worker_error is not None:
                        raise HilError(f"fault case {job.key}: the run failed in the harness: {worker_error}")
                    verdicts[job.index] = verdict
                    progress.set_postfix_str(job.key)
                    progress.update(1)
            finally:
                executor.close()
    return [verdicts[job.index] for job in jobs]

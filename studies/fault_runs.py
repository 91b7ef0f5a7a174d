"""The fault campaign's runs: one case with one controller on a private bus, judged
(`run_case`, against the Python or the C ECU), and every (case, controller) run of the
campaign as tasks of the campaigns' executors (`run_campaign`).
"""
from __future__ import annotations

import dataclasses
import logging
import types
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from hil.errors import HilError
from hil.faults import FaultSpec
from studies.fault_c_ecu import c_not_applicable, run_c_ecu_case
from studies.fault_cases import SCENARIO, FaultCase
from studies.fault_python_ecu import EcuLogCounter, run_ecu_case
from studies.fault_verdicts import Verdict, evaluate


def run_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
             duration_s: float | None = None, seed: int | None = None,
             source: object | None = None, ecu: str = "python") -> Verdict:
    """Run one case with one controller on a private virtual bus and judge it
    (``source`` names where the faults table came from in errors; default the case;
    ``ecu`` "c": the C executable on a loopback hub, as ``hil run --ecu c``)."""
    from hil.scenario import load_scenario
    from hil.session import SessionError, default_options, reference_path, run_hil
    from hil.time_master import TimeMasterError

    if ecu == "c" and (reason := c_not_applicable(case)) is not None:
        return Verdict(case.name, case.group, controller, f"{case.name}: {case.note}",
                       outcome="n/a", ecu=ecu, not_applicable=reason)
    if case.ecu_fault is not None:
        if ecu == "c":
            return run_c_ecu_case(case, controller, scenario_name, duration_s)
        return run_ecu_case(case, controller, scenario_name, duration_s)
    scenario = load_scenario(scenario_name)
    table = dict(case.table)
    if seed is not None:
        table["seed"] = seed
    spec = FaultSpec.from_mapping(table, source if source is not None else f"case {case.name!r}")
    changes: dict[str, Any] = {"faults": types.MappingProxyType(table)}
    if duration_s is not None:
        changes["duration_s"] = duration_s
    scenario = dataclasses.replace(scenario, **changes)
    description = "; ".join(f.describe() for f in spec.bus) or case.note or "no fault"
    if spec.bus and case.name != "cli":
        description = f"{case.name}: {description}"
    if case.group == "vehicle" and case.note and case.table:
        description = f"{case.name} ({case.note})"
    elif case.group == "vehicle":
        description = case.name if case.table else "no fault (baseline)"
    counter = EcuLogCounter()
    logger = logging.getLogger("firmware_sim")
    logger.addHandler(counter)
    result, error = None, None
    try:
        result = run_hil(scenario, default_options(controller, faults=spec, ecu=ecu))
    except (TimeMasterError, SessionError) as e:
        # The ECU died or stopped ACKing: a crash is a result here, not the end. Anything
        # else is a fault of the harness and propagates.
        error = e
    finally:
        logger.removeHandler(counter)
    verdict = evaluate(case, controller, result, error, counter.unexpected, counter.controller,
                       description, reference_path(scenario))
    verdict.ecu = ecu
    return verdict


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

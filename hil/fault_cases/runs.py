"""One fault case with one controller on a private bus, judged (`run_case`): the
run-and-verdict half of the fault campaign, against the Python or the C ECU. The
campaign that runs every case on the executors is ``studies.fault_campaign``.
"""
from __future__ import annotations

import dataclasses
import logging
import types
from typing import Any

from hil.errors import HilError
from hil.fault_cases.c_ecu import c_not_applicable, run_c_ecu_case
from hil.fault_cases.catalogue import SCENARIO, FaultCase
from hil.fault_cases.input_runs import run_input_case
from hil.fault_cases.python_ecu import EcuLogCounter, run_ecu_case
from hil.fault_cases.verdicts import Verdict, evaluate
from hil.faults import FaultSpec


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
    if case.ecu_fault is not None and case.ecu_fault["kind"] == "input":
        return run_input_case(case, controller, scenario_name, duration_s, ecu)
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

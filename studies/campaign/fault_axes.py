"""The ``fault_case`` runner's rules for a grid file (``studies.campaign.grid.load_grid``):
its cells are cases of the fault catalogue (``hil.fault_cases.catalogue.all_cases``, the
cases of ``make faults``), each run by ``hil.fault_cases.runs.run_case`` and judged
(``studies.campaign.fault_case_cell``).

- ``runner = ["fault_case"]`` stands alone on its axis (its cells are not scenario runs);
- the ``case`` axis names the cases (default: the whole catalogue, in its order);
- a case sets its own conditions: of the other axes only ``controller``, ``scenario`` (a
  shipped scenario's name: the catalogue's is ``dlc_high_mu``) and ``ecu`` are taken;
- a (case, controller) the case does not run (``FaultCase.controllers``) is left out, not
  an error (`fault_case_left_out`, counted in ``Grid.case_left_out``);
- ``[run] duration_s`` shortens every case's scenario (``--duration`` of ``make faults``);
  the other ``[run]`` keys belong to the scenario runners.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any

from studies.campaign.axes import FAULT_CASE_RUNNER, NO_CASE, GridError

#: The axes a ``fault_case`` grid may set.
FAULT_CASE_AXES = ("controller", "scenario", "ecu", "runner", "case")


@lru_cache(maxsize=1)
def fault_cases() -> dict[str, Any]:
    """The fault catalogue, name -> ``FaultCase``, in the catalogue's order."""
    from hil.fault_cases.catalogue import all_cases

    return {case.name: case for case in all_cases()}


def check_fault_case_axes(file: Path, axes: dict[str, tuple], axes_raw: Mapping[str, Any],
                          run: Mapping[str, Any]) -> None:
    """Check the ``fault_case`` runner's rules (module docstring) and fill in the case axis'
    default (``axes`` is changed in place).

    Raises:
        GridError: naming the file and the key.
    """
    duration = run.get("duration_s")
    if FAULT_CASE_RUNNER not in axes["runner"]:
        if "case" in axes_raw:
            raise GridError(f"{file}: axes.case names fault cases: it needs runner = [{FAULT_CASE_RUNNER!r}]")
        if duration is not None:
            raise GridError(f"{file}: run.duration_s is the {FAULT_CASE_RUNNER!r} runner's (a scenario "
                            "runner's cells take distance_m and margin_s)")
        return
    if len(axes["runner"]) > 1:
        raise GridError(f"{file}: axes.runner: {FAULT_CASE_RUNNER!r} stands alone (its cells are cases "
                        "of the fault catalogue, not scenario runs)")
    other = [name for name in axes_raw if name not in FAULT_CASE_AXES]
    if other:
        raise GridError(f"{file}: axes.{other[0]} with runner {FAULT_CASE_RUNNER!r}: a fault case sets "
                        f"its own conditions; its axes are {', '.join(FAULT_CASE_AXES)}")
    scenario_keys = sorted(set(run) - {"duration_s"})
    if scenario_keys:
        raise GridError(f"{file}: run.{scenario_keys[0]} with runner {FAULT_CASE_RUNNER!r}: it takes "
                        "only run.duration_s")
    from hil.scenario import list_scenarios

    for name in axes["scenario"]:
        if name not in list_scenarios():
            raise GridError(f"{file}: axes.scenario value {name!r} with runner {FAULT_CASE_RUNNER!r}: "
                            f"a shipped scenario's name ({', '.join(list_scenarios())})")
    known = fault_cases()
    if "case" not in axes_raw:
        axes["case"] = tuple(known)
    else:
        for name in axes["case"]:
            if name not in known:
                raise GridError(f"{file}: axes.case value {name!r}: not a case of the fault catalogue "
                                f"({', '.join(map(repr, known))})")
    if duration is not None and (isinstance(duration, bool) or not isinstance(duration, (int, float))
                                 or not math.isfinite(duration) or not 0 < duration <= 3600):
        raise GridError(f"{file}: run.duration_s = {duration!r}: must be a number of seconds in (0, 3600]")


def fault_case_left_out(cell: Any) -> bool:
    """A cell the grid leaves out: a ``fault_case`` cell whose case does not run its
    controller, or a scenario runner's cell with a case (none: the rules above)."""
    if cell.runner != FAULT_CASE_RUNNER:
        return cell.case != NO_CASE
    return cell.controller not in fault_cases()[cell.case].controllers

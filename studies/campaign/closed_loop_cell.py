"""A campaign cell on the ``closed_loop`` runner: the controller and the four-wheel plant in
one loop without CAN (``studies.closed_loop.run_closed_loop``, the runner of ``make
tables``), for grids too large for the bus (``make robustness``: 576 runs).

The cell's scenario is the one a ``hil`` cell of the same values runs, and its plant is the
one the HIL plant node would build for it (``hil.fault_injector.FaultInjector.vehicle``:
the steering lag of the ``lag_factor`` axis, the mass, the scenario's disturbances). The
grid refuses bus faults on this runner (:func:`studies.campaign.grid.load_grid`), since no
bus carries the frames here.

Row fields as a ``hil`` cell's (``studies.campaign.cell``), with these meanings here:

- ``completed`` / ``end_reason``: ``duration`` (ran to the end with |e_Y| <=
  :data:`~studies.campaign.cell.LEAVE_ROAD_M`), ``left_road`` (the runner stopped the run
  beyond that), ``stopped`` (the runner stopped it for another reason: a non-finite plant
  or command, a controller that raised), ``error`` (the run could not start);
- ``failure``: the runner's reason for stopping ("" when it ran to the end);
- ``step_p50_us`` / ``step_p99_us``: the controller's step time over the run after its
  first step (wall clock of the worker); ``overruns``: 0 (no real-time task here);
- ``steps``: control steps run.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from studies.campaign.model_controllers import model_factory

#: The runner's name in a grid's ``runner`` axis.
CLOSED_LOOP_RUNNER = "closed_loop"


def controller_for(name: str, model: Path | None, tuning: Any = None) -> Any:
    """The registry's controller ``name``, on the Koopman artefact ``model`` when given,
    from the ``ControllerTuning`` ``tuning`` when given (else ``controller/tuning.toml``)."""
    if model is not None:
        return model_factory(model, tuning)(name)
    if tuning is not None:
        from studies.campaign.tuning_override import build_controller

        return build_controller(name, tuning)
    from controller.registry import create_controller

    return create_controller(name)


def plant_for(scenario: Any) -> tuple[Any, Any]:
    """``(plant, command type)`` of ``scenario`` as the HIL plant node builds it: with the
    vehicle faults of its ``[faults]`` table (the lag axis), else ``Scenario.vehicle``."""
    from hil.fault_injector import FaultInjector
    from hil.faults import scenario_fault_spec
    from models.vehicle import VehicleCommand

    spec = scenario_fault_spec(scenario)  # None: the scenario has no [faults] table
    plant = FaultInjector(spec).vehicle(scenario) if spec is not None else None
    return (plant if plant is not None else scenario.vehicle()), VehicleCommand


def run_closed_loop_cell(scenario: Any, controller_name: str, model: Path | None,
                         row: dict[str, Any], leave_road_m: float, tuning: Any = None) -> dict[str, Any]:
    """Fill ``row`` with the result of one closed-loop run of ``scenario`` (see the module
    docstring); ``tuning``: the ``ControllerTuning`` to build the controller from (a cell of
    the ``tuning`` axis), None for the tuning file. An exception while building or running
    propagates to the caller, which records it."""
    from studies.closed_loop import run_closed_loop

    plant, command_type = plant_for(scenario)
    controller = (controller_for(controller_name, model) if tuning is None
                  else controller_for(controller_name, model, tuning))
    result = run_closed_loop(scenario, controller, plant=plant, command_type=command_type,
                             abort_lateral_error_m=leave_road_m)
    lateral, heading = result.tracking.lateral, result.tracking.heading
    completed = result.completed and lateral.max_abs <= leave_road_m
    if completed:
        reason = "duration"
    elif result.failure and lateral.max_abs <= leave_road_m:
        reason = "stopped"
    else:
        reason = "left_road"
    step_us = result.trace.step_time_s[1:] * 1e6
    row.update(e_y_rmse=lateral.rmse, e_y_max=lateral.max_abs, heading_rmse=heading.rmse,
               completed=int(completed), end_reason=reason, failure=result.failure or "",
               steps=len(result.trace), overruns=0,
               step_p50_us=float(np.percentile(step_us, 50)) if step_us.size else math.nan,
               step_p99_us=float(np.percentile(step_us, 99)) if step_us.size else math.nan)
    return row

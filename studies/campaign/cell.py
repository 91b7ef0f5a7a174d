"""One campaign cell: one lockstep run on the virtual bus through ``hil.session.run_hil``,
the same code path as ``python -m hil run --faults [--ecu c]``: the Python ECU in-process,
or the C ECU executable (``build/firmware/ecu``) as a process on the run's own loopback
socketcand hub; or, on the ``closed_loop`` runner, one run without CAN
(``studies.campaign.closed_loop_cell``, which says what its row's fields mean there).

:func:`run_cell` runs in a Ray worker (or in-process with ``--serial``); it takes a
:class:`CellJob` (plain data, so it pickles to any worker) and never raises for a failure
of the run: the error is in the returned row.

Row fields (``cells.csv``): the axes, then

- ``e_y_rmse`` / ``e_y_max`` (m), ``heading_rmse`` (rad): ``hil.metrics`` on the true pose
  at the control instants (as ``hil run`` prints them);
- ``completed`` (1 / 0) and ``end_reason``: ``duration`` (ran to the end, ECU ACTIVE,
  |e_Y| <= :data:`LEAVE_ROAD_M` throughout: completed), ``left_road``, ``never_active``,
  ``ended in MODE`` (the ECU's last mode was not ACTIVE), ``error``;
- ``step_p50_us`` / ``step_p99_us``: the ECU's control task time (CTRL_DIAG CYCLE_TIME_US)
  over its active cycles, wall clock of the worker; ``overruns``: the ECU's deadline
  overrun counter at the end (saturates at 15);
- ``wall_s``: the cell's wall time in its worker; ``error``: ``Type: message``;
- with ``CellJob.keep_trace`` (a grid's ``[run] keep_trace = true``), ``trace``: the true
  pose's errors at the control instants, ``{"time_s": [...], "e_y": [...], "progress":
  [...]}`` (s, m, m of path arc length; lists of equal length, to the micrometre), for
  studies that need more than the summary figures (``studies.disturbance_report``).
"""
from __future__ import annotations

import math
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from studies.campaign.closed_loop_cell import CLOSED_LOOP_RUNNER, run_closed_loop_cell
from studies.campaign.model_controllers import model_factory

#: |e_Y| above this (m) is off the road: the cell is not completed.
LEAVE_ROAD_M = 2.0
ROOT = Path(__file__).resolve().parent.parent.parent
#: The metric and run-fact columns of a row, after the axes.
RESULT_FIELDS = ("e_y_rmse", "e_y_max", "heading_rmse", "completed", "end_reason",
                 "step_p50_us", "step_p99_us", "overruns", "wall_s", "error")


@dataclass(frozen=True)
class CellJob:
    """What a worker needs for one cell.

    ``scenario_toml``: the cell's scenario file (``studies.campaign.grid.to_toml``) with
    ``path.file`` relative to the repository root (``{ROOT}/`` prefix), so the job is the
    same on any node with a checkout; ``model``: artefact path relative to the root, or
    None for the controllers' default; ``ecu``: "python" or "c" (``hil.session.RunOptions.ecu``);
    ``keep_trace``: add the e_Y trace to the row (``trace``, see the module docstring);
    ``runner``: "hil" (over CAN) or "closed_loop" (without CAN); ``closed_loop`` only:
    ``tuning_toml`` the base tuning file's text (None: ``controller/tuning.toml``),
    ``tuning_override`` the fields of the controller's table it replaces
    (``studies.campaign.tuning_override``), ``leave_road_m`` the |e_Y| (m) beyond which the
    run stops (None: :data:`LEAVE_ROAD_M`).
    """

    key: str
    controller: str
    scenario_toml: str
    model: str | None = None
    ecu: str = "python"
    keep_trace: bool = False
    runner: str = "hil"
    tuning_toml: str | None = None
    tuning_override: tuple[tuple[str, float], ...] = ()
    leave_road_m: float | None = None


def run_cell(job: CellJob) -> dict[str, Any]:
    """Run one cell; returns the result columns (:data:`RESULT_FIELDS`) and ``key``."""
    from can_defs.frames import CtrlMode
    from hil.bus import BusConfig, private_virtual_channel
    from hil.faults import scenario_fault_spec
    from hil.scenario import Scenario
    from hil.session import RunOptions, run_hil

    started = time.perf_counter()
    nan = math.nan
    row: dict[str, Any] = {"key": job.key, "e_y_rmse": nan, "e_y_max": nan, "heading_rmse": nan,
                           "completed": 0, "end_reason": "error", "step_p50_us": nan,
                           "step_p99_us": nan, "overruns": 0, "error": ""}
    try:
        with tempfile.TemporaryDirectory(prefix="campaign-cell-") as folder:
            file = Path(folder) / "scenario.toml"
            file.write_text(job.scenario_toml.replace("{ROOT}", str(ROOT)), encoding="utf-8")
            scenario = Scenario.load(file)
        if job.runner == CLOSED_LOOP_RUNNER:
            tuning = None
            if job.tuning_toml is not None or job.tuning_override:
                from studies.campaign.tuning_override import cell_tuning

                tuning = cell_tuning(job.tuning_toml, job.controller, job.tuning_override)
            run_closed_loop_cell(scenario, job.controller, ROOT / job.model if job.model else None,
                                 row, LEAVE_ROAD_M if job.leave_road_m is None else job.leave_road_m,
                                 tuning=tuning)
            row["wall_s"] = time.perf_counter() - started
            return row
        bus = BusConfig("virtual", private_virtual_channel())
        if job.ecu == "c":
            # the executable reads another model as its data file (``--model`` of hil run);
            # a controller factory exists only in-process
            options = RunOptions(controller=job.controller, bus=bus, ecu="c",
                                 faults=scenario_fault_spec(scenario),
                                 model=ROOT / job.model if job.model else None)
        else:
            factory = model_factory(ROOT / job.model) if job.model else None
            options = RunOptions(controller=job.controller, bus=bus,
                                 faults=scenario_fault_spec(scenario), controller_factory=factory)
        result = run_hil(scenario, options)
    except Exception as e:  # noqa: BLE001 - recorded in the row; the campaign goes on
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc(limit=8)
        row["wall_s"] = time.perf_counter() - started
        return row
    ecu = result.ecu_trace
    active = ecu["ctrl_mode"] == int(CtrlMode.ACTIVE)
    lateral, heading = result.tracking.lateral, result.tracking.heading
    row.update(e_y_rmse=lateral.rmse, e_y_max=lateral.max_abs, heading_rmse=heading.rmse,
               overruns=int(ecu["overruns"][-1]) if len(ecu["overruns"]) else 0)
    if np.any(active):
        cycle_us = ecu["cycle_time_us"][active]
        row["step_p50_us"] = float(np.percentile(cycle_us, 50))
        row["step_p99_us"] = float(np.percentile(cycle_us, 99))
    if not np.any(active):
        reason = "never_active"
    elif lateral.max_abs > LEAVE_ROAD_M:
        reason = "left_road"
    elif int(ecu["ctrl_mode"][-1]) != int(CtrlMode.ACTIVE):
        reason = f"ended in {CtrlMode(int(ecu['ctrl_mode'][-1])).name}"
    else:
        reason = "duration"
    if job.keep_trace:
        row["trace"] = _error_trace(result, scenario)
    row.update(end_reason=reason, completed=int(reason == "duration"),
               wall_s=time.perf_counter() - started)
    return row


def _error_trace(result: Any, scenario: Any) -> dict[str, list[float]]:
    """The run's e_Y and path progress at the control instants (module docstring)."""
    from hil.session import control_instant_errors, reference_path

    times, errors = control_instant_errors(result.plant_trace, reference_path(scenario))
    return {"time_s": [round(float(t), 3) for t in times],
            "e_y": [round(float(e), 6) for e in errors.lateral_error],
            "progress": [round(float(s), 6) for s in errors.progress]}

"""Closed-loop simulation without CAN: one controller drives the plant through a scenario
with the HIL's timing, for the study of ``make tables`` (paper Tables II/III, Figs 8/9).

Timing, as the lockstep HIL of the CAN contract does it:

- virtual time advances in ticks of 5 ms; the plant is integrated tick by tick with the
  command applied at the start of the tick (zero-order hold);
- the plant publishes its outputs every 10 ms, so the controller, which runs every 25 ms
  (t = 0, 25, 50, ... ms), sees the newest published sample: from t itself when t is a
  multiple of 10 ms, else from t - 5 ms (the HIL's sample age, without CAN quantisation);
- the planner's target speed is the scenario's profile at t;
- the command computed at t is applied from t until the next control step.

The plant is the scenario's (``Scenario.vehicle``: its mu, mass and ``[disturbances]``, as
the HIL's plant node has it); the controller sees what its sensors report (a yaw-rate bias
on, a steering offset not seen).

Recorded per control step: the true plant state at t (what the metrics use), the command,
the errors to the path, the solver's own diagnostics, and the wall-clock time of
``controller.step`` (``time.perf_counter`` around the call: the runner may read the clock,
the control law may not).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from controller.base import STEER_LIMIT_RAD, Command, Controller, StepDebug, VehicleSample
from controller.reference import ReferencePath, lateral_error
from hil.errors import StudyError
from hil.metrics import ComputeTimeStats, TrackingMetrics, tracking_metrics, wrap_angle
from hil.scenario import Scenario

#: Lockstep tick of the contract (ms).
TICK_MS = 5
#: Plant publication period (VEH_DYN / VEH_POSE_*), ms.
PLANT_PERIOD_MS = 10
#: Control task period Ts (ms).
CONTROL_PERIOD_MS = 25
#: A run is stopped (failed) once the vehicle is this far from the path (m): it has left
#: any road the study stands for, and the rest of the run would only cost time.
ABORT_LATERAL_ERROR_M = 10.0


class Plant(Protocol):
    """What the runner needs of the plant (``models.vehicle.FourWheelVehicle`` has it)."""

    def reset(self, vx: float = 0.0, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None: ...

    def step(self, command: Any, dt: float) -> None: ...

    def outputs(self) -> Any: ...


#: Builds the plant's command object from (drive_torque, steer_angle).
CommandFactory = Callable[..., Any]

_TRACE_FIELDS = (
    "time_s", "x", "y", "yaw", "vx", "vy", "yaw_rate", "steer_angle", "drive_torque",
    "target_speed", "steer_cmd", "torque_cmd", "lateral_error", "heading_error",
    "progress", "solver_status", "solver_iterations", "solve_time_s", "step_time_s",
    "fallback", "slack_max", "observer_reset",
)


@dataclass(frozen=True)
class ClosedLoopTrace:
    """Time series of a run, one entry per control step; every array has shape (n,).

    Plant values are the TRUE state at the control instant (m, m/s, rad, rad/s, N m);
    ``steer_cmd`` / ``torque_cmd`` what the controller sent; ``lateral_error`` (m, left
    positive), ``heading_error`` (rad) and ``progress`` (m of arc length) of the foot point
    on the path (``hil.metrics``); ``solver_status`` the
    ``SolverStatus`` value; ``solve_time_s`` the solver's own figure; ``step_time_s`` the
    wall-clock time of ``controller.step``.
    """

    time_s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    yaw_rate: np.ndarray
    steer_angle: np.ndarray
    drive_torque: np.ndarray
    target_speed: np.ndarray
    steer_cmd: np.ndarray
    torque_cmd: np.ndarray
    lateral_error: np.ndarray
    heading_error: np.ndarray
    progress: np.ndarray
    solver_status: np.ndarray
    solver_iterations: np.ndarray
    solve_time_s: np.ndarray
    step_time_s: np.ndarray
    fallback: np.ndarray
    slack_max: np.ndarray
    observer_reset: np.ndarray

    def __len__(self) -> int:
        return int(self.time_s.size)

    def columns(self) -> dict[str, np.ndarray]:
        """All series by name (for ``np.savez``)."""
        return {name: getattr(self, name) for name in _TRACE_FIELDS}


@dataclass(frozen=True)
class ClosedLoopResult:
    """Outcome of one run: the trace, whether it completed, and its metrics.

    ``failure`` says why a run stopped early (None when ``completed``). ``compute_time``
    leaves out the first step, which includes one-off set-up (solver construction, JIT).
    """

    scenario: str
    controller: str
    trace: ClosedLoopTrace
    completed: bool
    failure: str | None
    tracking: TrackingMetrics
    compute_time: ComputeTimeStats
    steer_limit_held: bool
    fallback_steps: int

    def save_npz(self, file: Path) -> None:
        """Write the trace plus run facts to a compressed ``.npz``."""
        np.savez_compressed(
            file, scenario=self.scenario, controller=self.controller,
            completed=self.completed, failure=self.failure or "", **self.trace.columns()
        )


def control_steps(scenario: Scenario) -> int:
    """Number of control steps a complete run of ``scenario`` has."""
    n_ticks = int(round(scenario.duration_s * 1000.0)) // TICK_MS
    return -(-n_ticks * TICK_MS // CONTROL_PERIOD_MS)


def default_plant(scenario: Scenario) -> tuple[Plant, CommandFactory]:
    """The project's four-wheel plant with the scenario's mu, mass and disturbances
    (``Scenario.vehicle``, as the HIL plant node builds it), and its command type."""
    from models.vehicle import VehicleCommand

    return scenario.vehicle(), VehicleCommand


def load_reference_path(scenario: Scenario) -> ReferencePath:
    """``controller.reference.ReferencePath`` of the scenario's (already validated) CSV."""
    return ReferencePath.from_csv(scenario.path_file)


def run_closed_loop(
    scenario: Scenario,
    controller: Controller,
    *,
    plant: Plant | None = None,
    command_type: CommandFactory | None = None,
    reference_path: ReferencePath | None = None,
    abort_lateral_error_m: float = ABORT_LATERAL_ERROR_M,
    on_control_step: Callable[[int], None] | None = None,
    plant_period_ms: int = PLANT_PERIOD_MS,
) -> ClosedLoopResult:
    """Run ``controller`` on ``scenario`` for its whole duration (see the module docstring).

    Args:
        scenario: the run's conditions.
        controller: any ``controller.base.Controller``; reset and given the path here.
        plant: a plant to use instead of :func:`default_plant` (tests); then
            ``command_type`` builds its commands (default ``models.vehicle.VehicleCommand``).
        reference_path: the path handed to ``controller.set_path`` and measured against
            (default: the scenario's CSV).
        abort_lateral_error_m: stop the run, failed, beyond this |e_Y| (m).
        on_control_step: called with the step index after each control step (progress bars).
        plant_period_ms: how often the plant publishes (a multiple of the 5 ms tick); the
            contract's 10 ms by default; 5 ms gives the controller a fresh sample every step
            (to separate the effect of the contract's sample age from the control law's).

    Returns:
        The :class:`ClosedLoopResult`. A run that stops early (non-finite or diverged plant
        state, non-finite command, an exception from the controller, |e_Y| too large) is
        returned with ``completed`` False and the trace up to that point; it is not raised.
    """
    if plant_period_ms <= 0 or plant_period_ms % TICK_MS:
        raise StudyError(f"plant_period_ms = {plant_period_ms}: must be a positive multiple "
                         f"of the {TICK_MS} ms tick")
    if plant is None:
        plant, default_command = default_plant(scenario)
        command_type = command_type or default_command
    if command_type is None:
        from models.vehicle import VehicleCommand

        command_type = VehicleCommand
    if reference_path is None:
        reference_path = load_reference_path(scenario)

    start = scenario.start
    plant.reset(vx=start.speed_mps, x=start.x_m, y=start.y_m, yaw=start.yaw_rad)
    controller.reset()
    controller.set_path(reference_path)

    n_ticks = int(round(scenario.duration_s * 1000.0)) // TICK_MS
    rows: list[dict[str, float]] = []
    failure: str | None = None
    published = plant.outputs()
    applied = Command(steer_angle=0.0, drive_torque=0.0)
    for tick in range(n_ticks):
        t_ms = tick * TICK_MS
        if t_ms % plant_period_ms == 0:
            published = plant.outputs()
        if t_ms % CONTROL_PERIOD_MS == 0:
            true_state = _true_outputs(plant)
            if not _finite_outputs(true_state):
                failure = f"plant state not finite at t = {t_ms / 1000:.3f} s"
                break
            target_speed = scenario.target_speed(t_ms / 1000.0)
            sample = _sample_from(published, target_speed)
            started = time.perf_counter()
            try:
                command, debug = controller.step(sample)
            except Exception as e:  # noqa: BLE001 - the contract says step never raises
                failure = f"controller.step raised at t = {t_ms / 1000:.3f} s: {e!r}"
                break
            step_time = time.perf_counter() - started
            foot = lateral_error(reference_path, true_state.x, true_state.y, true_state.yaw)
            rows.append(_row(t_ms, true_state, target_speed, command, debug, step_time, foot))
            if not (math.isfinite(command.steer_angle) and math.isfinite(command.drive_torque)):
                failure = f"non-finite command at t = {t_ms / 1000:.3f} s: {command}"
                break
            if abs(foot.lateral_error) > abort_lateral_error_m:
                failure = (f"|e_Y| = {abs(foot.lateral_error):.2f} m > {abort_lateral_error_m} m "
                           f"at t = {t_ms / 1000:.3f} s (X = {true_state.x:.1f} m)")
                break
            applied = command
            if on_control_step is not None:
                on_control_step(len(rows) - 1)
        try:
            plant.step(command_type(drive_torque=applied.drive_torque,
                                    steer_angle=applied.steer_angle), TICK_MS / 1000.0)
        except Exception as e:  # noqa: BLE001 - e.g. models' VehicleDivergedError
            failure = f"plant failed at t = {t_ms / 1000:.3f} s: {e!r}"
            break
    return _result(scenario, controller, rows, failure)


def _true_outputs(plant: Plant) -> Any:
    """The plant's true state: ``true_outputs()`` where it has one (a scenario's sensor bias
    and steering offset left out), else ``outputs()``."""
    true_outputs = getattr(plant, "true_outputs", None)
    return true_outputs() if true_outputs is not None else plant.outputs()


def _finite_outputs(outputs: Any) -> bool:
    return all(math.isfinite(getattr(outputs, name)) for name in
               ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque"))


def _sample_from(outputs: Any, target_speed: float) -> VehicleSample:
    """The ECU's view of one published plant sample plus the planner's request."""
    return VehicleSample(
        vx=float(outputs.vx), vy=float(outputs.vy), yaw_rate=float(outputs.yaw_rate),
        x=float(outputs.x), y=float(outputs.y), yaw=float(wrap_angle(outputs.yaw)),
        steer_angle=float(outputs.steer_angle), drive_torque=float(outputs.drive_torque),
        target_speed=float(target_speed),
    )


def _row(t_ms: int, state: Any, target_speed: float, command: Command, debug: StepDebug,
         step_time: float, foot: Any) -> dict[str, float]:
    return {
        "time_s": t_ms / 1000.0, "x": state.x, "y": state.y, "yaw": float(wrap_angle(state.yaw)),
        "vx": state.vx, "vy": state.vy, "yaw_rate": state.yaw_rate,
        "steer_angle": state.steer_angle, "drive_torque": state.drive_torque,
        "target_speed": target_speed, "steer_cmd": command.steer_angle,
        "torque_cmd": command.drive_torque, "lateral_error": foot.lateral_error,
        "heading_error": foot.heading_error, "progress": foot.progress,
        "solver_status": int(debug.status), "solver_iterations": debug.iterations,
        "solve_time_s": debug.solve_time_s, "step_time_s": step_time,
        "fallback": bool(debug.fallback), "slack_max": debug.slack_max,
        "observer_reset": bool(debug.observer_reset),
    }


def _result(scenario: Scenario, controller: Controller, rows: list[dict[str, float]],
            failure: str | None) -> ClosedLoopResult:
    if not rows:
        raise StudyError(f"{scenario.name}: no control step ran ({failure or 'duration < Ts'})")
    int_fields = {"solver_status", "solver_iterations"}
    bool_fields = {"fallback", "observer_reset"}
    columns = {}
    for name in _TRACE_FIELDS:
        dtype = np.int64 if name in int_fields else bool if name in bool_fields else float
        columns[name] = np.array([row[name] for row in rows], dtype=dtype)
    trace = ClosedLoopTrace(**columns)
    # Step 0 carries one-off set-up work (solver construction, first factorisation).
    timed = trace.step_time_s[1:] if len(trace) > 1 else trace.step_time_s
    return ClosedLoopResult(
        scenario=scenario.name,
        controller=getattr(controller, "name", "") or type(controller).__name__,
        trace=trace,
        completed=failure is None,
        failure=failure,
        tracking=tracking_metrics(trace.lateral_error, trace.heading_error),
        compute_time=ComputeTimeStats.of(timed),
        steer_limit_held=bool(np.all(np.abs(trace.steer_cmd) <= STEER_LIMIT_RAD + 1e-9)),
        fallback_steps=int(np.sum(trace.fallback)),
    )


__all__ = [
    "ABORT_LATERAL_ERROR_M", "CONTROL_PERIOD_MS", "ClosedLoopResult", "ClosedLoopTrace",
    "PLANT_PERIOD_MS", "TICK_MS", "control_steps", "default_plant", "load_reference_path", "run_closed_loop",
]

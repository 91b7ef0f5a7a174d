"""The one interface every lateral controller offers: ``step(sample) -> (command, debug)``.

Control math only: nothing here touches the bus, the clock or files. Solve times in the
debug record come from the solvers' own statistics (OSQP ``info.solve_time``, IPOPT
``t_wall_total``), so the law stays a pure function of its inputs and state.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

# The solver outcome is the contract's CTRL_DIAG.QP_STATUS, one enum: the ECU sends it as is.
from can_defs.frames import QpStatus as SolverStatus
from models.measurement import VehicleMeasurement

#: Physical steering limit of eq. 22 (rad); the contract's STEER_ANGLE_CMD limit too.
STEER_LIMIT_RAD = 0.3
#: Control period Ts of the paper and of the CAN contract (s).
CONTROL_PERIOD_S = 0.025


@dataclass(frozen=True)
class VehicleSample(VehicleMeasurement):
    """One consistent measurement of the vehicle plus the planner's request.

    The eight measured fields (and ``state()`` / ``pose()``) are those of
    `models.measurement.VehicleMeasurement`, in its order; ``target_speed`` (m/s) is the
    planner's desired longitudinal velocity. Positional construction takes the nine
    values in that order. ``sample_age_s`` (keyword only, s; default 0) is how old the
    measurement was when the control task started, computed by the ECU from its clock and
    handed in as data; only the delay compensation reads it (``MpcTuning.delay_compensation_s``).
    """

    target_speed: float
    sample_age_s: float = field(default=0.0, kw_only=True)

    @classmethod
    def from_measurement(cls, measurement: VehicleMeasurement, target_speed: float,
                         sample_age_s: float = 0.0) -> "VehicleSample":
        """The controller's input from a measurement (or any subclass of it), a target speed
        and the measurement's age at the task start (s)."""
        return cls(**measurement.measurement_values(), target_speed=target_speed, sample_age_s=sample_age_s)


def sample_is_finite(sample: VehicleSample) -> bool:
    """Whether every value of ``sample`` (the eight measured ones and the target speed) is
    finite: a controller steps only on such samples and falls back otherwise."""
    return all(math.isfinite(value) for value in (
        sample.vx, sample.vy, sample.yaw_rate, sample.x, sample.y, sample.yaw,
        sample.steer_angle, sample.drive_torque, sample.target_speed))


@dataclass(frozen=True)
class Command:
    """Actuator request: front wheel angle (rad, left positive) and total torque (N m)."""

    steer_angle: float
    drive_torque: float


@dataclass(frozen=True)
class StepDebug:
    """What one control step did, for CTRL_DIAG, logs and tests.

    ``predicted_pose`` has shape (n_p, 3) ([x, y, yaw] over the horizon) and
    ``predicted_state`` shape (n_p, 3) ([vx, vy, yaw_rate]); empty (0, 3) when not run.
    """

    status: SolverStatus
    iterations: int = 0
    solve_time_s: float = 0.0
    cost: float = float("nan")
    predicted_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    predicted_state: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    fallback: bool = False
    slack_max: float = 0.0
    observer_reset: bool = False


class Controller(ABC):
    """Base of ESO-DKMPC, DKMPC, LMPC and NMPC (one file each, chosen by name)."""

    #: Registry name, e.g. ``"eso-dkmpc"``.
    name: str = ""

    @abstractmethod
    def set_path(self, path: "ReferencePath") -> None:  # noqa: F821 (controller.reference)
        """Select the reference path to follow; resets progress along it."""

    @abstractmethod
    def reset(self) -> None:
        """Forget all internal state (warm starts, observer, progress)."""

    @abstractmethod
    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        """One control step at Ts = 0.025 s. Never raises for finite samples; the
        returned command is always within the limits (fallback on solver failure)."""

    def set_time_budget(self, seconds: float | None) -> None:
        """Wall-clock budget of one step's solver (s), None for none. The ECU sets it in real
        time only: a step that runs out falls back as on any solver failure. A lockstep run
        never sets it, so its commands stay independent of the machine's speed. Only a
        solver whose time varies widely needs it (NMPC); the default ignores it."""

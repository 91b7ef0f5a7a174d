"""Test doubles for the closed-loop runner (no tests here): a kinematic plant, a pure-pursuit
controller and a scripted controller.

Deliberately simple and independent of the vehicle models and of the MPCs, so the runner's
timing and bookkeeping are tested on their own; the plant reports the shared
`models.measurement.VehicleMeasurement` record, as the four-wheel plant does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from controller.base import STEER_LIMIT_RAD, Command, Controller, SolverStatus, StepDebug, \
    VehicleSample
from controller.reference import PathTracker, ReferencePath
from models.measurement import VehicleMeasurement, wrap_angle

WHEELBASE_M = 2.7


@dataclass(frozen=True)
class KinematicCommand:
    drive_torque: float
    steer_angle: float


@dataclass
class KinematicPlant:
    """Kinematic bicycle; the steer follows the command at once, saturated at 0.3 rad;
    ``speed_gain`` (m/s^2 per N m) turns torque into acceleration. Logs every step."""

    speed_gain: float = 1e-3
    vx: float = 0.0
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    steer: float = 0.0
    torque: float = 0.0
    steps: list[tuple[float, float, float]] = field(default_factory=list)  # (dt, steer, torque)

    def reset(self, vx: float = 0.0, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        self.vx, self.x, self.y, self.yaw = vx, x, y, yaw
        self.steer = self.torque = 0.0
        self.steps.clear()

    def step(self, command: KinematicCommand, dt: float) -> None:
        self.steps.append((dt, command.steer_angle, command.drive_torque))
        self.steer = float(np.clip(command.steer_angle, -STEER_LIMIT_RAD, STEER_LIMIT_RAD))
        self.torque = command.drive_torque
        self.vx += self.speed_gain * self.torque * dt
        self.x += self.vx * math.cos(self.yaw) * dt
        self.y += self.vx * math.sin(self.yaw) * dt
        self.yaw += self.vx / WHEELBASE_M * math.tan(self.steer) * dt

    def outputs(self) -> VehicleMeasurement:
        return VehicleMeasurement(self.vx, 0.0, self.vx / WHEELBASE_M * math.tan(self.steer),
                                  self.x, self.y, wrap_angle(self.yaw), self.steer, self.torque)


class PurePursuit(Controller):
    """Pure pursuit on the path with a P speed loop; records the samples it was given."""

    name = "pure-pursuit"

    def __init__(self, lookahead_m: float = 6.0, speed_gain: float = 200.0) -> None:
        self.lookahead_m = lookahead_m
        self.speed_gain = speed_gain
        self.tracker: PathTracker | None = None
        self.samples: list[VehicleSample] = []

    def set_path(self, path: ReferencePath) -> None:
        self.tracker = PathTracker(path)

    def reset(self) -> None:
        self.samples = []
        if self.tracker is not None:
            self.tracker.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        self.samples.append(sample)
        assert self.tracker is not None
        foot = self.tracker.update(sample.x, sample.y, sample.yaw)
        target = self.tracker.path.pose_at(np.array([foot.progress + self.lookahead_m]))[0]
        alpha = math.atan2(target[1] - sample.y, target[0] - sample.x) - sample.yaw
        steer = math.atan(2 * WHEELBASE_M * math.sin(alpha) / self.lookahead_m)
        steer = float(np.clip(steer, -STEER_LIMIT_RAD, STEER_LIMIT_RAD))
        torque = self.speed_gain * (sample.target_speed - sample.vx)
        return Command(steer, torque), StepDebug(SolverStatus.SOLVED, iterations=1)


class ScriptedController(Controller):
    """Sends ``steer_of(k)`` at step k (may be out of limits or NaN); raises at
    ``raise_at`` to test the runner's failure handling."""

    name = "scripted"

    def __init__(self, steer_of, raise_at: int | None = None) -> None:
        self.steer_of = steer_of
        self.raise_at = raise_at
        self.k = 0
        self.samples: list[VehicleSample] = []

    def set_path(self, path: ReferencePath) -> None:
        pass

    def reset(self) -> None:
        self.k = 0
        self.samples = []

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        if self.raise_at is not None and self.k == self.raise_at:
            raise RuntimeError("scripted failure")
        self.samples.append(sample)
        steer = self.steer_of(self.k)
        self.k += 1
        return Command(steer, 0.0), StepDebug(SolverStatus.SOLVED, fallback=self.k % 2 == 0)

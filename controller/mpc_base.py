"""What the four steering MPCs share: reference, speed control, fallback, limits, debug.

A subclass only plans: ``_plan(sample, drive_torque, reference) -> Plan``. This base turns
the plan into a command or, when the plan failed (status not SOLVED / SOLVED_INACCURATE,
or a non-finite value), into the defined fallback: the shifted previous solution
(``steer[age]`` of the last good plan), else the previous command held. Non-finite samples
give the fallback with status NOT_RUN. The last step always clips to the limits.

With the grip envelope on (``MpcTuning.grip_slip_excess`` > 0), every valid sample first
advances the grip estimate (``controller.grip_envelope``), and ``yaw_rate_bound`` holds the
yaw-rate bound the subclass's plan puts on eq. 21's yaw-rate rows.
"""
from __future__ import annotations

import math
from abc import abstractmethod
from collections import deque
from dataclasses import dataclass

import numpy as np

from controller.base import (CONTROL_PERIOD_S, STEER_LIMIT_RAD, Command, Controller, SolverStatus, StepDebug,
                             VehicleSample, sample_is_finite)
from controller.delay_compensation import COMMAND_HISTORY
from controller.grip_envelope import GripEnvelope, RearAxle, envelope_on
from controller.longitudinal import SpeedController
from controller.reference import PathTracker, ReferencePath
from controller.steady_slip import measured_slip, reference_bend, slip_target
from controller.tuning import LongitudinalTuning, MpcTuning

#: Control period of the paper and of the CAN contract (s).
TS = CONTROL_PERIOD_S
_GOOD = (SolverStatus.SOLVED, SolverStatus.SOLVED_INACCURATE)


@dataclass(frozen=True)
class Plan:
    """One solver run: steer sequence (Nc,), predicted_pose / predicted_state (Np, 3)."""

    status: SolverStatus
    steer: np.ndarray
    iterations: int
    solve_time_s: float
    cost: float
    predicted_pose: np.ndarray
    predicted_state: np.ndarray
    slack_max: float = 0.0


class SteeringMpc(Controller):
    """Base of the steering MPCs: decoupled structure (P speed control + MPC steering)."""

    def __init__(self, tuning: MpcTuning, longitudinal: LongitudinalTuning) -> None:
        self.tuning = tuning
        self.ts = TS
        self._speed = SpeedController(longitudinal)
        self._tracker: PathTracker | None = None
        self._observer_reset = False
        # The nominal bicycle's rear axle only where the envelope is on: the tables that
        # leave it off need no vehicle file.
        self.grip = GripEnvelope(tuning, RearAxle.nominal()) if envelope_on(tuning) else None
        self.reset()

    # -- interface ---------------------------------------------------------------------
    def set_path(self, path: ReferencePath) -> None:
        """Follow ``path`` from now on; progress is searched afresh on the next step."""
        self._tracker = PathTracker(path)

    def reset(self) -> None:
        """Forget plans, previous command, progress (and, in subclasses, observers)."""
        self._plan_steer: np.ndarray | None = None  # last good steer sequence (Nc,)
        self._plan_age = 0  # steps since that plan was computed
        self._last_command: Command | None = None
        # The steer commands sent, newest last: the ones in flight over the delay window.
        self._command_history: deque[float] = deque(maxlen=COMMAND_HISTORY)
        self.slip_target = 0.0  # rad: how far the last step moved the heading target
        self.yaw_rate_bound = math.inf  # rad/s: the grip envelope's bound of the step (inf: none)
        if self.grip is not None:
            self.grip.reset()
        if self._tracker is not None:
            self._tracker.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        """One control step (see ``Controller.step``)."""
        if self._tracker is None or not sample_is_finite(sample):
            return self._fallback(SolverStatus.NOT_RUN, torque=None)
        torque = self._speed.torque(sample.vx, sample.target_speed)
        # The grip estimate reads the measurement, as the observer does, before any delay shift.
        self.yaw_rate_bound = self.grip.update(sample) if self.grip is not None else math.inf
        sample = self._prepare(sample, torque)
        projection = self._tracker.update(sample.x, sample.y, sample.yaw)
        reference = self._tracker.horizon_reference(projection.progress, sample.vx,
                                                    self.tuning.prediction_horizon, self.ts, sample.yaw)
        self._observer_reset = False
        plan = self._plan(sample, torque, self.target_reference(reference, sample))
        if plan.status not in _GOOD or not (math.isfinite(plan.steer.sum()) and math.isfinite(plan.cost)):
            return self._fallback(plan.status, torque, plan, sample)
        self._plan_steer = np.clip(plan.steer, -STEER_LIMIT_RAD, STEER_LIMIT_RAD)
        self._plan_age = 0
        command = self._finish(float(self._plan_steer[0]), torque)
        self._after_command(sample, command)
        return command, StepDebug(status=plan.status, iterations=plan.iterations,
                                  solve_time_s=plan.solve_time_s, cost=plan.cost,
                                  predicted_pose=plan.predicted_pose,
                                  predicted_state=plan.predicted_state, fallback=False,
                                  slack_max=plan.slack_max, observer_reset=self._observer_reset)

    def target_reference(self, reference: np.ndarray, sample: VehicleSample) -> np.ndarray:
        """The poses (Np, 3) the cost pulls towards: the path's, with the heading moved by
        the sample's side slip, bounded and faded (``controller.steady_slip``), so that the
        yaw cost holds the course on the path. With ``slip_target_limit`` 0 (off) the path's
        poses as they are, at no cost per step."""
        tuning = self.tuning
        if tuning.slip_target_limit == 0.0:
            return reference
        self.slip_target = slip_target(measured_slip(sample.vy, sample.vx), reference_bend(reference[:, 2]),
                                       tuning.slip_target_limit, tuning.slip_target_gate)
        if self.slip_target == 0.0:
            return reference
        target = reference.copy()
        target[:, 2] -= self.slip_target
        return target

    # -- for subclasses ------------------------------------------------------------------
    @abstractmethod
    def _plan(self, sample: VehicleSample, drive_torque: float, reference: np.ndarray) -> Plan:
        """Solve the MPC for this sample; ``reference`` (Np, 3) the target poses at steps
        1..Np (the path's, its heading moved by ``target_reference``)."""

    def _prepare(self, sample: VehicleSample, drive_torque: float) -> VehicleSample:
        """The sample the step plans from (reference, pose, weights): the measured one; the
        QP MPCs move it over the delay window when delay compensation is on."""
        return sample

    def _after_command(self, sample: VehicleSample, command: Command) -> None:
        """Hook after a command was produced for a valid sample (observer update)."""

    def previous_steer(self, sample: VehicleSample) -> float:
        """u_{-1} of eq. 15: the last command, else (first step) the measured wheel angle."""
        if self._last_command is not None:
            return self._last_command.steer_angle
        return min(max(sample.steer_angle, -STEER_LIMIT_RAD), STEER_LIMIT_RAD)

    def shifted_plan(self, sample: VehicleSample) -> np.ndarray:
        """Warm start / linearisation point (Nc,): the last good plan shifted to now (by one
        step, more after fallbacks; last value repeated), else the previous steer held."""
        n_ctrl = self.tuning.control_horizon
        if self._plan_steer is None:
            return np.full(n_ctrl, self.previous_steer(sample))
        remaining = self._plan_steer[self._plan_age + 1:]
        return np.concatenate((remaining, np.full(n_ctrl - remaining.size, self._plan_steer[-1])))

    # -- internals -------------------------------------------------------------------------
    def _fallback(self, status: SolverStatus, torque: float | None, plan: Plan | None = None,
                  sample: VehicleSample | None = None) -> tuple[Command, StepDebug]:
        """Shifted previous solution, else the previous command; flagged ``fallback``.

        ``sample`` is given when it was valid (solver failure): hooks still see the command.
        """
        previous = self._last_command
        if self._plan_steer is not None and self._plan_age + 1 < self._plan_steer.size:
            self._plan_age += 1
            steer = float(self._plan_steer[self._plan_age])
        else:
            self._plan_steer = None
            steer = previous.steer_angle if previous is not None else 0.0
        if torque is None:
            torque = previous.drive_torque if previous is not None else 0.0
        command = self._finish(steer, torque)
        if sample is not None:
            self._after_command(sample, command)
        debug = StepDebug(status=status, fallback=True,
                          iterations=plan.iterations if plan is not None else 0,
                          solve_time_s=plan.solve_time_s if plan is not None else 0.0,
                          observer_reset=self._observer_reset)
        self._observer_reset = False
        return command, debug

    def _finish(self, steer: float, torque: float) -> Command:
        """Final guard: finite and within the limits, whatever came before."""
        steer = min(max(float(steer), -STEER_LIMIT_RAD), STEER_LIMIT_RAD) if math.isfinite(steer) else 0.0
        torque = self._speed.clip(torque) if math.isfinite(torque) else 0.0
        self._last_command = Command(steer_angle=steer, drive_torque=torque)
        self._command_history.append(steer)
        return self._last_command

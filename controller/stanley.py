"""Stanley: a geometric path-tracking baseline with no vehicle model (issue 35 item 5).

The law of Hoffmann, Tomlin, Montemerlo and Thrun (2007), "Autonomous automobile
trajectory tracking for off-road driving", with the two additions production lateral
controllers usually carry, each a tuning field of ``[stanley]`` (``StanleyTuning``)::

    e_fa   cross-track error of the front axle (m, left of the path positive)
    psi_e  vehicle yaw minus path yaw at the front axle's foot point (rad, wrapped)
    kappa  path curvature at that foot point (1/m, left turn positive)

    steer_raw = -psi_e - atan(k e_fa / (k_soft + vx))          # Hoffmann et al., eq. 8
                + k_r (vx kappa - yaw_rate)                     # yaw-rate damping

then a first-order low-pass of time constant ``steer_time_constant`` and a rate limit of
``steer_rate_limit`` on the command, and the steering limit of eq. 22. The signs follow
this project's conventions (steer left positive, ``PathProjection``): a vehicle left of
the path or yawed left of it steers right. The yaw-rate term pulls the measured yaw rate
towards the path's (vx kappa): it damps the yaw oscillation the pure law shows at speed and
supplies the steady yaw rate of a curve, which the pure law can only get from an offset.

The torque is the shared P speed controller's, as for the MPCs (decoupled structure). The
front axle lies ``front_axle_distance`` (the nominal lf of ``models.bicycle``) ahead of the
centre of gravity along the vehicle's heading; its foot point comes from
``controller.reference.PathTracker``, whose windowed search cannot jump to another part of
the path.

No solver runs: every valid step reports ``SOLVED`` with 0 iterations and 0 s. A
non-finite sample (or no path) gives the fallback of ``controller.mpc_base``: the previous
command held (torque included), status ``NOT_RUN``, ``debug.fallback``; a finite sample
whose law comes out non-finite (positions near overflow) holds the previous steer with the
P controller's torque, status ``NUMERICAL_ERROR``. The last step
clips the steer to +-0.3 rad and the torque to the tuning's limits and replaces any
non-finite value by 0, so ``step`` never raises and never commands out of limits.
"""
from __future__ import annotations

import math

import numpy as np

from controller.base import (STEER_LIMIT_RAD, Command, Controller, SolverStatus, StepDebug, VehicleSample,
                             sample_is_finite)
from controller.errors import TuningError
from controller.longitudinal import SpeedController
from controller.reference import PathTracker, ReferencePath
from controller.tuning import ControllerTuning, LongitudinalTuning, StanleyTuning

#: Control period of the CAN contract (s), as ``controller.mpc_base.TS``.
TS = 0.025


def path_curvature(path: ReferencePath) -> np.ndarray:
    """Curvature d(yaw)/ds at each path point (1/m, left turn positive), shape (n,).

    Central differences of the unwrapped yaw over the arc length (one-sided at the ends).
    """
    return np.gradient(np.asarray(path.yaw, dtype=float), np.asarray(path.s, dtype=float))


def stanley_steer(heading_error: float, front_cross_track_error: float, vx: float,
                  yaw_rate: float, curvature: float, tuning: StanleyTuning) -> float:
    """The unfiltered Stanley steer angle (rad, left positive), before filter and limits.

    Args:
        heading_error: vehicle yaw minus path yaw at the front axle's foot point (rad).
        front_cross_track_error: signed distance of the front axle to the path (m, left +).
        vx: measured longitudinal speed (m/s); negative values count as 0.
        yaw_rate: measured yaw rate (rad/s).
        curvature: path curvature at the foot point (1/m).
        tuning: the gains.
    """
    speed = max(vx, 0.0)
    cross_track = math.atan(tuning.cross_track_gain * front_cross_track_error
                            / (tuning.softening_speed + speed))
    damping = tuning.yaw_rate_gain * (speed * curvature - yaw_rate)
    return -heading_error - cross_track + damping


class Stanley(Controller):
    """The Stanley law with yaw-rate damping, a command low-pass and a rate limit."""

    name = "stanley"

    def __init__(self, tuning: StanleyTuning, longitudinal: LongitudinalTuning,
                 front_axle_distance: float) -> None:
        """Args:
            tuning: the ``[stanley]`` table.
            longitudinal: the shared P speed controller's table.
            front_axle_distance: centre of gravity to front axle (m), > 0.

        Raises:
            TuningError: ``front_axle_distance`` not a finite positive number.
        """
        if not (math.isfinite(front_axle_distance) and front_axle_distance > 0.0):
            raise TuningError(f"stanley: front_axle_distance must be a finite number > 0 m, "
                              f"got {front_axle_distance!r}")
        self.tuning = tuning
        self.ts = TS
        self.front_axle_distance = float(front_axle_distance)
        self._speed = SpeedController(longitudinal)
        self._tracker: PathTracker | None = None
        self._curvature = np.zeros(0)
        self._last_command: Command | None = None
        # Share of the way to the raw steer the low-pass moves per step (1: no filter).
        self._filter_share = TS / (tuning.steer_time_constant + TS)
        self._max_steer_change = tuning.steer_rate_limit * TS

    @classmethod
    def from_tuning(cls, tuning: ControllerTuning) -> "Stanley":
        """Build with ``[stanley]``, ``[longitudinal]`` and the nominal lf of
        ``models.bicycle.nominal_model_params`` (the geometry the baselines get)."""
        from models.bicycle import nominal_model_params

        return cls(tuning.stanley, tuning.longitudinal, nominal_model_params().lf)

    # -- interface ---------------------------------------------------------------------
    def set_path(self, path: ReferencePath) -> None:
        """Follow ``path`` from now on; progress is searched afresh on the next step."""
        self._tracker = PathTracker(path)
        self._curvature = path_curvature(path)

    def reset(self) -> None:
        """Forget the previous command and the progress along the path."""
        self._last_command = None
        if self._tracker is not None:
            self._tracker.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        """One control step (see ``Controller.step``); never raises."""
        if self._tracker is None or not sample_is_finite(sample):
            return self._fallback()
        torque = self._speed.torque(sample.vx, sample.target_speed)
        front_x = sample.x + self.front_axle_distance * math.cos(sample.yaw)
        front_y = sample.y + self.front_axle_distance * math.sin(sample.yaw)
        with np.errstate(all="ignore"):  # absurd positions end in the NUMERICAL_ERROR fallback
            projection = self._tracker.update(front_x, front_y, sample.yaw)
        curvature = float(np.interp(projection.progress, self._tracker.path.s, self._curvature))
        raw = stanley_steer(projection.heading_error, projection.lateral_error, sample.vx,
                            sample.yaw_rate, curvature, self.tuning)
        if not math.isfinite(raw):  # finite but absurd samples (positions near overflow)
            return self._fallback(SolverStatus.NUMERICAL_ERROR, torque)
        previous = self._previous_steer(sample)
        filtered = previous + self._filter_share * (raw - previous)
        change = min(max(filtered - previous, -self._max_steer_change), self._max_steer_change)
        command = self._finish(previous + change, torque)
        return command, StepDebug(status=SolverStatus.SOLVED, iterations=0, solve_time_s=0.0)

    # -- internals -------------------------------------------------------------------------
    def _previous_steer(self, sample: VehicleSample) -> float:
        """The last command, else (first step) the measured wheel angle within the limit:
        where the filter and the rate limit start from."""
        if self._last_command is not None:
            return self._last_command.steer_angle
        return min(max(sample.steer_angle, -STEER_LIMIT_RAD), STEER_LIMIT_RAD)

    def _fallback(self, status: SolverStatus = SolverStatus.NOT_RUN,
                  torque: float | None = None) -> tuple[Command, StepDebug]:
        """The previous steer held (zero before any), flagged ``fallback``; the torque given
        (the P controller's for a valid sample), else the previous one."""
        previous = self._last_command
        steer = previous.steer_angle if previous is not None else 0.0
        if torque is None:
            torque = previous.drive_torque if previous is not None else 0.0
        return self._finish(steer, torque), StepDebug(status=status, fallback=True)

    def _finish(self, steer: float, torque: float) -> Command:
        """Final guard: finite and within the limits, whatever came before."""
        steer = min(max(float(steer), -STEER_LIMIT_RAD), STEER_LIMIT_RAD) if math.isfinite(steer) else 0.0
        torque = self._speed.clip(torque) if math.isfinite(torque) else 0.0
        self._last_command = Command(steer_angle=steer, drive_torque=torque)
        return self._last_command

"""Tracking and compute-time metrics of a closed-loop run, as in the paper's Tables II/III.

- Lateral deviation ``e_Y``: signed distance from the vehicle's centre of gravity to the
  reference path, positive when the vehicle is LEFT of the path (ISO 8855, +Y left).
- Heading error: vehicle yaw minus the path tangent's yaw at the foot point, wrapped to
  [-pi, pi).
- Each summarised as Max (of |.|), Avg (mean of |.|) and RMSE.
- Compute time per control step: mean, median, p99 and max.

The foot point is ``controller.reference.lateral_error``: the same projection the
controllers' ``PathTracker`` uses, searched over the whole path (nearest segment). That is
exact for paths that never come back within ~|e_Y| of themselves, as the double lane
change; one piece of code thus defines e_Y for the controllers and for the tables.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controller.reference import ReferencePath, lateral_error
from hil.errors import MetricsError
from models.measurement import wrap_angle  # re-exported for the studies

__all__ = ["CONTROL_PERIOD_MS", "ComputeTimeStats", "ErrorStats", "PathErrors", "TrackingMetrics",
           "control_instant_errors", "control_instant_metrics", "path_errors", "reference_path",
           "tracking_metrics", "wrap_angle"]

#: Control period of the ECU (contract: 25 ms); a run's metrics are sampled at these instants.
CONTROL_PERIOD_MS = 25


@dataclass(frozen=True)
class PathErrors:
    """Errors of n poses to a path, each array shape (n,): ``lateral_error`` (m, left
    positive), ``heading_error`` (rad, wrapped) and ``progress`` (m of arc length of the
    foot point)."""

    lateral_error: np.ndarray
    heading_error: np.ndarray
    progress: np.ndarray


def path_errors(pose: np.ndarray, path: ReferencePath) -> PathErrors:
    """Lateral deviation and heading error of a pose trace.

    Args:
        pose: ``[x, y, yaw]`` (m, m, rad), shape (n, 3), finite.
        path: the reference path.
    """
    pose = np.asarray(pose, dtype=float)
    if pose.ndim != 2 or pose.shape[1] != 3:
        raise MetricsError(f"pose must have shape (n, 3), got {pose.shape}")
    if not np.all(np.isfinite(pose)):
        bad = int(np.argwhere(~np.isfinite(pose))[0, 0])
        raise MetricsError(f"pose {bad} is not finite: {pose[bad].tolist()}")
    feet = [lateral_error(path, x, y, yaw) for x, y, yaw in pose]
    return PathErrors(
        lateral_error=np.array([foot.lateral_error for foot in feet]),
        heading_error=np.array([foot.heading_error for foot in feet]),
        progress=np.array([foot.progress for foot in feet]),
    )

@dataclass(frozen=True)
class ErrorStats:
    """Max |e|, mean |e| and RMSE of one error signal (same unit as the signal)."""

    max_abs: float
    mean_abs: float
    rmse: float

    @classmethod
    def of(cls, error: np.ndarray) -> "ErrorStats":
        """Statistics of an error signal, shape (n,), n >= 1, all finite."""
        error = _finite_1d(error, "error")
        magnitude = np.abs(error)
        return cls(
            max_abs=float(magnitude.max()),
            mean_abs=float(magnitude.mean()),
            rmse=float(np.sqrt(np.mean(error**2))),
        )

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class TrackingMetrics:
    """Table II / III row: lateral deviation (m) and heading error (rad) statistics."""

    lateral: ErrorStats
    heading: ErrorStats

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {"lateral_error_m": self.lateral.as_dict(),
                "heading_error_rad": self.heading.as_dict()}


@dataclass(frozen=True)
class ComputeTimeStats:
    """Wall-clock time per control step (s): mean, median, 99th percentile, max, count."""

    mean_s: float
    median_s: float
    p99_s: float
    max_s: float
    steps: int

    @classmethod
    def of(cls, step_times_s: np.ndarray) -> "ComputeTimeStats":
        """Statistics of per-step times (s), shape (n,), n >= 1, all finite and >= 0."""
        times = _finite_1d(step_times_s, "step_times_s")
        if np.any(times < 0.0):
            raise MetricsError(f"step_times_s: negative time {float(times.min())}")
        return cls(
            mean_s=float(times.mean()),
            median_s=float(np.median(times)),
            p99_s=float(np.percentile(times, 99.0)),
            max_s=float(times.max()),
            steps=int(times.size),
        )

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def tracking_metrics(lateral_error: np.ndarray, heading_error: np.ndarray) -> TrackingMetrics:
    """Table II / III statistics from error traces, each shape (n,)."""
    return TrackingMetrics(ErrorStats.of(lateral_error), ErrorStats.of(heading_error))


def _finite_1d(values: np.ndarray, name: str) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size == 0:
        raise MetricsError(f"{name} must have shape (n >= 1,), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise MetricsError(f"{name} has {int(np.sum(~np.isfinite(values)))} non-finite values")
    return values


# --- the true pose of a run at the control instants ---------------------------------------

def reference_path(scenario: Any) -> ReferencePath:
    """The scenario's (``hil.scenario.Scenario``) reference path: what e_Y is measured to."""
    return ReferencePath.from_csv(scenario.path_file)


def control_instant_errors(plant_trace: dict[str, np.ndarray], path: ReferencePath) -> tuple[np.ndarray, PathErrors]:
    """The true pose's errors to the path at t = 0, 25, 50, ... ms.

    Args:
        plant_trace: the plant node's trace (``time``, ``x``, ``y``, ``yaw``: (n_ticks,)).
        path: the reference path (``controller.reference.ReferencePath``).

    Returns:
        (the control instants (s), shape (k,); their e_Y, heading error and progress, (k,) each).
    """
    time_ms = np.round(plant_trace["time"] * 1000.0).astype(np.int64)
    at_control = time_ms % CONTROL_PERIOD_MS == 0
    pose = np.column_stack([plant_trace["x"][at_control], plant_trace["y"][at_control],
                            plant_trace["yaw"][at_control]])
    return plant_trace["time"][at_control], path_errors(pose, path)


def control_instant_metrics(plant_trace: dict[str, np.ndarray], path: ReferencePath) -> TrackingMetrics:
    """e_Y and heading-error statistics of the true pose at t = 0, 25, 50, ... ms
    (:func:`control_instant_errors`)."""
    _, errors = control_instant_errors(plant_trace, path)
    return tracking_metrics(errors.lateral_error, errors.heading_error)

"""Forward prediction of a vehicle sample over a gap in the measurements (dead reckoning).

Used by the ECU in DEGRADED: from the last good sample, the planar velocities are held
constant and the pose is integrated with the kinematics of eq. 20,

    X_{k+1} = X_k + Ts (Vx cos(theta_k) - Vy sin(theta_k))
    Y_{k+1} = Y_k + Ts (Vx sin(theta_k) + Vy cos(theta_k))
    theta_{k+1} = theta_k + Ts omega_r,

in steps of at most Ts (the last step shortened to the remaining time). Pure functions:
no bus, no clock.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from controller.base import VehicleSample
from models.measurement import wrap_angle

#: Control period of the paper (s), the default integration step.
DEFAULT_TS = 0.025


def predict_pose(pose: np.ndarray, velocity: np.ndarray, elapsed_s: float,
                 ts: float = DEFAULT_TS) -> np.ndarray:
    """Pose after ``elapsed_s`` at constant body-frame velocities (eq. 20).

    Args:
        pose: [x, y, yaw] (m, m, rad), shape (3,).
        velocity: [vx, vy, yaw_rate] (m/s, m/s, rad/s), shape (3,).
        elapsed_s: prediction time, >= 0, s.
        ts: largest integration step, > 0, s.

    Returns:
        [x, y, yaw] with yaw wrapped to [-pi, pi), shape (3,).

    Raises:
        ValueError: when an argument is non-finite, negative or has the wrong shape.
    """
    pose = np.asarray(pose, dtype=float)
    velocity = np.asarray(velocity, dtype=float)
    if pose.shape != (3,) or velocity.shape != (3,):
        raise ValueError(f"pose and velocity must have shape (3,), got {pose.shape} and {velocity.shape}")
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(velocity))):
        raise ValueError(f"non-finite pose {pose} or velocity {velocity}")
    if not (math.isfinite(elapsed_s) and elapsed_s >= 0.0):
        raise ValueError(f"elapsed_s must be finite and >= 0, got {elapsed_s}")
    if not (math.isfinite(ts) and ts > 0.0):
        raise ValueError(f"ts must be finite and > 0, got {ts}")
    x, y, yaw = (float(value) for value in pose)
    vx, vy, yaw_rate = (float(value) for value in velocity)
    n_steps = math.ceil(elapsed_s / ts - 1e-9) if elapsed_s > 0.0 else 0
    for step in range(n_steps):
        dt = min(ts, elapsed_s - step * ts)
        x, y, yaw = (x + dt * (vx * math.cos(yaw) - vy * math.sin(yaw)),
                     y + dt * (vx * math.sin(yaw) + vy * math.cos(yaw)),
                     yaw + dt * yaw_rate)
    return np.array([x, y, wrap_angle(yaw)])


def predict_sample(sample: VehicleSample, elapsed_s: float,
                   ts: float = DEFAULT_TS) -> VehicleSample:
    """``sample`` moved forward by ``elapsed_s``: same velocities, steering, torque and
    target speed; pose from `predict_pose`."""
    x, y, yaw = predict_pose(sample.pose(), sample.state(), elapsed_s, ts)
    return replace(sample, x=float(x), y=float(y), yaw=float(yaw))

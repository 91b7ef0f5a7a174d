"""Pose kinematics of eq. 20 and its linearisation for the real-time-iteration QP.

States are body-frame velocities [vx, vy, yaw_rate]; poses global [X, Y, yaw]. With the
dynamic states over the horizon affine in the steering sequence U (Nc,),
states(U) = free + gain @ U, the pose of eq. 20 is linearised about a nominal sequence:
pose(U) ~= pose_nominal + jacobian @ (U - U_nominal). The yaw is exactly linear in U
(it only sums yaw rates); X and Y are not (cos/sin of the yaw, products with vx, vy).
"""
from __future__ import annotations

import numpy as np


def rollout_pose(pose0: np.ndarray, states: np.ndarray, ts: float) -> np.ndarray:
    """Integrate eq. 20 (explicit Euler at ``ts``).

    pose0: (3,) [X, Y, yaw] at step 0; states: (n, 3) [vx, vy, yaw_rate] at steps 0..n-1.
    Returns (n, 3): poses at steps 1..n.
    """
    yaw = pose0[2] + ts * np.concatenate(([0.0], np.cumsum(states[:, 2])))  # (n + 1,)
    cos_yaw, sin_yaw = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    vx, vy = states[:, 0], states[:, 1]
    poses = np.empty((states.shape[0], 3))
    poses[:, 0] = pose0[0] + ts * np.cumsum(vx * cos_yaw - vy * sin_yaw)
    poses[:, 1] = pose0[1] + ts * np.cumsum(vx * sin_yaw + vy * cos_yaw)
    poses[:, 2] = yaw[1:]
    return poses


def linearise_pose(pose0: np.ndarray, nominal_states: np.ndarray, state_gain: np.ndarray,
                   ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose of eq. 20 about a nominal state trajectory and its Jacobian in U.

    pose0: (3,); nominal_states: (n, 3) states at steps 0..n-1 for the nominal U;
    state_gain: (n, 3, n_u) d states / d U. Returns (nominal poses (n, 3) at steps 1..n,
    jacobian (n, 3, n_u)). Same arithmetic as ``rollout_pose`` (kept separate: this runs
    every control step, so it shares the cos/sin and velocity terms with the Jacobian).
    """
    n = nominal_states.shape[0]
    yaw = np.empty(n + 1)
    yaw[0] = 0.0
    np.cumsum(nominal_states[:, 2], out=yaw[1:])
    yaw *= ts
    yaw += pose0[2]
    cos_yaw, sin_yaw = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    vx, vy = nominal_states[:, 0], nominal_states[:, 1]
    x_rate = vx * cos_yaw - vy * sin_yaw  # dX/dt at steps 0..n-1
    y_rate = vx * sin_yaw + vy * cos_yaw
    poses = np.empty((n, 3))
    poses[:, 0] = pose0[0] + ts * np.cumsum(x_rate)
    poses[:, 1] = pose0[1] + ts * np.cumsum(y_rate)
    poses[:, 2] = yaw[1:]
    # d yaw_j / dU at steps j = 0..n-1 (step 0 is measured: zero), and at steps 1..n.
    d_yaw = np.zeros((n + 1, state_gain.shape[2]))
    np.cumsum(state_gain[:, 2, :], axis=0, out=d_yaw[1:])
    d_yaw *= ts
    jacobian = np.empty_like(state_gain)
    cos_col, sin_col = cos_yaw[:, None], sin_yaw[:, None]
    gain_vx, gain_vy = state_gain[:, 0, :], state_gain[:, 1, :]
    # d(x_rate) = cos dvx - sin dvy - y_rate dyaw;  d(y_rate) = sin dvx + cos dvy + x_rate dyaw
    np.cumsum(cos_col * gain_vx - sin_col * gain_vy - y_rate[:, None] * d_yaw[:-1], axis=0, out=jacobian[:, 0, :])
    np.cumsum(sin_col * gain_vx + cos_col * gain_vy + x_rate[:, None] * d_yaw[:-1], axis=0, out=jacobian[:, 1, :])
    jacobian[:, :2, :] *= ts
    jacobian[:, 2, :] = d_yaw[1:]
    return poses, jacobian

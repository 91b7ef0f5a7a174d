"""Pose kinematics of eq. 20 and its linearisation for the real-time-iteration QP.

States are body-frame velocities [vx, vy, yaw_rate]; poses global [X, Y, yaw]. With the
dynamic states over the horizon affine in the steering sequence U (Nc,),
states(U) = free + gain @ U, the pose of eq. 20 is linearised about a nominal sequence:
pose(U) ~= pose_nominal + jacobian @ (U - U_nominal). The yaw is exactly linear in U
(it only sums yaw rates); X and Y are not (cos/sin of the yaw, products with vx, vy).

Step i moves the position along the heading yaw_i + advance * ts * r_i. With advance 0
(the default) that is eq. 20's explicit Euler; with 0.5 it is the step's midpoint heading,
exact for a yaw rate constant over the step up to the chord's length (a relative
(r ts)^2 / 24). Why the option: on an arc explicit Euler lags the heading by half a step's
turn, r ts / 2, so the predicted path runs outside the true one by that angle times the
distance ahead (R 50 m at 50 km/h: 3.5 mrad, 4.9 cm one second ahead), and the MPC steers
inside the arc to make up for it (docs/controllers.md, "The pose step"). With advance 0
the arithmetic is eq. 20's bit for bit (adding 0.0 * r leaves the yaw as it is).
"""
from __future__ import annotations

import numpy as np


def rollout_pose(pose0: np.ndarray, states: np.ndarray, ts: float, heading_advance: float = 0.0) -> np.ndarray:
    """Integrate eq. 20 at ``ts``, each step along yaw_i + heading_advance * ts * r_i.

    pose0: (3,) [X, Y, yaw] at step 0; states: (n, 3) [vx, vy, yaw_rate] at steps 0..n-1.
    Returns (n, 3): poses at steps 1..n.
    """
    yaw = pose0[2] + ts * np.concatenate(([0.0], np.cumsum(states[:, 2])))  # (n + 1,)
    heading = yaw[:-1] + (heading_advance * ts) * states[:, 2]
    cos_yaw, sin_yaw = np.cos(heading), np.sin(heading)
    vx, vy = states[:, 0], states[:, 1]
    poses = np.empty((states.shape[0], 3))
    poses[:, 0] = pose0[0] + ts * np.cumsum(vx * cos_yaw - vy * sin_yaw)
    poses[:, 1] = pose0[1] + ts * np.cumsum(vx * sin_yaw + vy * cos_yaw)
    poses[:, 2] = yaw[1:]
    return poses


def linearise_pose(pose0: np.ndarray, nominal_states: np.ndarray, state_gain: np.ndarray,
                   ts: float, heading_advance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
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
    heading = yaw[:-1] + (heading_advance * ts) * nominal_states[:, 2]
    cos_yaw, sin_yaw = np.cos(heading), np.sin(heading)
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
    d_heading = d_yaw[:-1] + (heading_advance * ts) * state_gain[:, 2, :]
    jacobian = np.empty_like(state_gain)
    cos_col, sin_col = cos_yaw[:, None], sin_yaw[:, None]
    gain_vx, gain_vy = state_gain[:, 0, :], state_gain[:, 1, :]
    # d(x_rate) = cos dvx - sin dvy - y_rate dheading;  d(y_rate) = sin dvx + cos dvy + x_rate dheading
    np.cumsum(cos_col * gain_vx - sin_col * gain_vy - y_rate[:, None] * d_heading, axis=0, out=jacobian[:, 0, :])
    np.cumsum(sin_col * gain_vx + cos_col * gain_vy + x_rate[:, None] * d_heading, axis=0, out=jacobian[:, 1, :])
    jacobian[:, :2, :] *= ts
    jacobian[:, 2, :] = d_yaw[1:]
    return poses, jacobian

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
    jacobian (n, 3, n_u)).
    """
    poses = rollout_pose(pose0, nominal_states, ts)
    yaw_steps = np.concatenate(([pose0[2]], poses[:-1, 2]))  # yaw at steps 0..n-1
    cos_yaw, sin_yaw = np.cos(yaw_steps)[:, None], np.sin(yaw_steps)[:, None]
    vx, vy = nominal_states[:, 0:1], nominal_states[:, 1:2]
    gain_vx, gain_vy, gain_rate = state_gain[:, 0, :], state_gain[:, 1, :], state_gain[:, 2, :]
    d_yaw_next = ts * np.cumsum(gain_rate, axis=0)  # d yaw_{i+1} / dU, i = 0..n-1
    d_yaw = np.vstack((np.zeros((1, state_gain.shape[2])), d_yaw_next[:-1]))  # steps 0..n-1
    jacobian = np.empty_like(state_gain)
    jacobian[:, 0, :] = ts * np.cumsum(cos_yaw * gain_vx - sin_yaw * gain_vy
                                       - (vx * sin_yaw + vy * cos_yaw) * d_yaw, axis=0)
    jacobian[:, 1, :] = ts * np.cumsum(sin_yaw * gain_vx + cos_yaw * gain_vy
                                       + (vx * cos_yaw - vy * sin_yaw) * d_yaw, axis=0)
    jacobian[:, 2, :] = d_yaw_next
    return poses, jacobian

"""Delay compensation (issue 37): start the MPC's prediction where the vehicle will be when
the new command takes effect, not where it was when it was measured.

The delay from a sample to its command's effect is the sample's age at the task start
(``VehicleSample.sample_age_s``, from the ECU) plus the fixed part of the tuning,
``MpcTuning.delay_compensation_s`` (the task time and the actuator's dead time). Over that
window the vehicle still moves under the commands already sent; as Autoware's MPC does, the
measured state is predicted forward over it through the controller's own discrete model with
those commands, and the horizon starts from there. The model steps at Ts, so a delay of
``whole_steps`` Ts plus a ``fraction`` of one is covered by whole steps, then one more step
interpolated linearly (:func:`forward_state`). Pure functions: no clock, no bus.

The command in flight during grid step j (0-based, from the sample's time) of a window of m
whole steps is the one sent m - j steps before the newest (:func:`delay_window`): the newest
command acts over the last (fractional) step, the one before it over the step before, and
so on; where the history is shorter (the first steps), the oldest known command stands in.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: Commands kept for the window (the newest last): 8 steps of 25 ms, 0.2 s, above the
#: tuning's 0.1 s bound plus any age a fresh sample has. A longer window reuses the oldest.
COMMAND_HISTORY = 8


@dataclass(frozen=True)
class DelayWindow:
    """The delay as ``whole_steps`` model steps plus ``fraction`` of one, and the command in
    flight during each of the ``whole_steps + 1`` grid steps it touches, ``inputs``
    (whole_steps + 1,), rad."""

    whole_steps: int
    fraction: float
    inputs: np.ndarray


def total_delay(fixed_delay_s: float, sample_age_s: float) -> float:
    """The window (s): the tuning's fixed part plus the sample's age; 0 when the fixed part
    is 0 (compensation off). An age that is not finite or negative counts as 0 (the ECU's
    freshness rules, not the control law, decide about such a sample)."""
    if fixed_delay_s <= 0.0:
        return 0.0
    age = sample_age_s if math.isfinite(sample_age_s) and sample_age_s > 0.0 else 0.0
    return fixed_delay_s + age


def delay_window(delay_s: float, ts: float, history: Sequence[float]) -> DelayWindow:
    """The window of ``delay_s`` (> 0) at model step ``ts`` with ``history`` the commands
    sent, oldest first, newest last (at least one)."""
    # floor of the quotient, not delay_s // ts (Python's floor division can differ by one at
    # a step boundary), as the C core computes it (firmware/src/ecu_delay.c).
    whole = min(int(math.floor(delay_s / ts)), COMMAND_HISTORY - 1)
    fraction = min(delay_s / ts - whole, 1.0)
    newest = len(history) - 1
    inputs = np.array([history[max(newest - (whole - j), 0)] for j in range(whole + 1)])
    return DelayWindow(whole, fraction, inputs)


def forward_state(step: Callable[[np.ndarray, float], np.ndarray], start: np.ndarray,
                  window: DelayWindow) -> np.ndarray:
    """The model's state at the end of ``window``: ``step(state, steer) -> next state`` (the
    controller's own discrete model at Ts, shape kept) applied with the commands in flight,
    the last step interpolated by the window's fraction."""
    state = start
    for steer in window.inputs[:window.whole_steps]:
        state = step(state, float(steer))
    following = step(state, float(window.inputs[window.whole_steps]))
    return state + window.fraction * (following - state)


def pose_after(pose0: np.ndarray, states: np.ndarray, ts: float, window: DelayWindow,
               heading_advance: float = 0.0) -> np.ndarray:
    """The pose [X, Y, yaw] (3,) at the end of ``window``: eq. 20 integrated as
    ``controller.pose_kinematics.rollout_pose`` does (each step along its yaw plus
    ``heading_advance`` of its own turn) from ``pose0`` (3,) with ``states``
    (whole_steps + 1, 3), [vx, vy, yaw_rate] at the grid steps 0..whole_steps, the last
    step for the fraction only."""
    pose = np.array(pose0, dtype=float)
    durations = [ts] * window.whole_steps + [window.fraction * ts]
    for (vx, vy, yaw_rate), dt in zip(states, durations):
        heading = pose[2] + heading_advance * dt * yaw_rate
        cos_yaw, sin_yaw = math.cos(heading), math.sin(heading)
        pose = pose + dt * np.array([vx * cos_yaw - vy * sin_yaw, vx * sin_yaw + vy * cos_yaw, yaw_rate])
    return pose

"""The SAFE_STOP actuator request: steering back to straight at a bounded rate, braking
torque until standstill.

This is a fixed reaction, not a control law: a rate limiter towards zero and a constant
braking torque.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SafeStopCommand:
    """Steering angle (rad) and drive torque (N m, negative = braking) of one SAFE_STOP cycle."""

    steer_angle: float
    drive_torque: float


def safe_stop_command(previous_steer: float, standstill: bool, period_s: float,
                      steer_rate_rad_s: float, brake_torque_nm: float) -> SafeStopCommand:
    """Move the steering towards 0 by at most ``steer_rate_rad_s * period_s`` and brake.

    At standstill the torque is 0: a negative wheel torque on a vehicle at rest would
    drive it backwards, and the plant holds it with zero torque.
    """
    max_step = steer_rate_rad_s * period_s
    steer = previous_steer - min(max(previous_steer, -max_step), max_step)
    torque = 0.0 if standstill else -abs(brake_torque_nm)
    return SafeStopCommand(steer_angle=steer, drive_torque=torque)

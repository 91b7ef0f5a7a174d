"""The last check before a command reaches the bus.

A command that is not finite or is outside the limits is refused and replaced by a safe
fallback: the previous valid steering angle held and zero drive torque. The ECU sets FAULTS
bit 2 (solver fallback) when that happens.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_sim.config import (DBC_DRIVE_TORQUE_MAX_NM, DBC_DRIVE_TORQUE_MIN_NM,
                                 DBC_STEER_MAX_RAD, DBC_STEER_MIN_RAD)


@dataclass(frozen=True)
class GuardLimits:
    """Limits of the guard: |steer| <= steer_limit_rad, |torque| <= drive_torque_limit_nm,
    both also inside the DBC's representable range."""

    steer_limit_rad: float
    drive_torque_limit_nm: float

    def steer_range(self) -> tuple[float, float]:
        """(min, max) admissible steering angle, rad."""
        return (max(-self.steer_limit_rad, DBC_STEER_MIN_RAD),
                min(self.steer_limit_rad, DBC_STEER_MAX_RAD))

    def torque_range(self) -> tuple[float, float]:
        """(min, max) admissible drive torque, N m."""
        return (max(-self.drive_torque_limit_nm, DBC_DRIVE_TORQUE_MIN_NM),
                min(self.drive_torque_limit_nm, DBC_DRIVE_TORQUE_MAX_NM))


@dataclass(frozen=True)
class GuardedCommand:
    """What goes on the bus; ``refused`` names why the requested command was replaced."""

    steer_angle: float
    drive_torque: float
    refused: str | None = None


def guard_command(steer_angle: float, drive_torque: float, limits: GuardLimits,
                  previous_valid_steer: float) -> GuardedCommand:
    """Pass the command if finite and within ``limits``, else the safe fallback.

    ``previous_valid_steer`` must itself be within the limits (the ECU only keeps steering
    angles that passed this guard); it is clamped again so the fallback can never be out of
    range.
    """
    steer_min, steer_max = limits.steer_range()
    torque_min, torque_max = limits.torque_range()
    reason: str | None = None
    if not (isinstance(steer_angle, (int, float)) and math.isfinite(steer_angle)):
        reason = f"steer_angle {steer_angle!r} is not finite"
    elif not (isinstance(drive_torque, (int, float)) and math.isfinite(drive_torque)):
        reason = f"drive_torque {drive_torque!r} is not finite"
    elif not steer_min <= steer_angle <= steer_max:
        reason = f"steer_angle {steer_angle:.6g} rad outside [{steer_min}, {steer_max}]"
    elif not torque_min <= drive_torque <= torque_max:
        reason = f"drive_torque {drive_torque:.6g} N m outside [{torque_min}, {torque_max}]"
    if reason is None:
        return GuardedCommand(float(steer_angle), float(drive_torque))
    held = previous_valid_steer if math.isfinite(previous_valid_steer) else 0.0
    held = min(max(held, steer_min), steer_max)
    return GuardedCommand(held, 0.0, refused=reason)

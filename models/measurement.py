"""The vehicle measurement every package shares, and the one angle wrap.

`VehicleMeasurement` holds the eight quantities the plant reports over CAN (the signals
of VEH_DYN, VEH_POSE_XY and VEH_POSE_YAW, ``docs/can-contract.md``). It is one type for
the three places that need this record: the plant's outputs (``models.vehicle``,
``FourWheelVehicle.outputs()``), the controller's input (``controller.base.VehicleSample``
adds the planner's target speed) and the ECU's assembled sample
(``models.plant_sample.PlantMeasurement`` adds the shared alive counter). It lives in
``models`` because ``models`` imports neither ``controller`` nor ``firmware_sim``, while
both of them may import ``models``.

`wrap_angle` is the wrap to [-pi, pi) of the contract's YAW signal, used by the plant,
the controllers' path geometry and the ECU's dead reckoning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import overload

import numpy as np

_TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(angle: float) -> float: ...


@overload
def wrap_angle(angle: np.ndarray) -> np.ndarray: ...


def wrap_angle(angle: float | np.ndarray) -> float | np.ndarray:
    """Wrap an angle (rad) to [-pi, pi).

    An angle already inside the range is returned unchanged, bit for bit (the modulo
    formula alone would round it by up to one ulp of pi), so wrapping is idempotent and
    a wrapped value passes through the ECU exactly.

    Args:
        angle: a scalar, or an array of any shape.

    Returns:
        A Python float for a scalar (including numpy scalars), else an array of the same
        shape as ``angle``.
    """
    if isinstance(angle, (float, int)):
        value = float(angle)
        if -math.pi <= value < math.pi:
            return value
        return (value + math.pi) % _TWO_PI - math.pi
    values = np.asarray(angle, dtype=float)
    inside = (values >= -math.pi) & (values < math.pi)
    return np.where(inside, values, (values + math.pi) % _TWO_PI - math.pi)


@dataclass(frozen=True)
class VehicleMeasurement:
    """One sample of the vehicle as the CAN contract carries it.

    Units: m/s, m/s, rad/s, m, m, rad, rad, N m. ``vx`` and ``vy`` are body-frame
    velocities of the centre of gravity (``vy`` left positive), ``yaw_rate`` counter-
    clockwise positive; ``x``, ``y`` the global position of the centre of gravity;
    ``yaw`` the heading wrapped to [-pi, pi) (`wrap_angle`); ``steer_angle`` the measured
    front wheel angle and ``drive_torque`` the measured total wheel torque.
    """

    vx: float
    vy: float
    yaw_rate: float
    x: float
    y: float
    yaw: float
    steer_angle: float
    drive_torque: float

    def state(self) -> np.ndarray:
        """Planar dynamic state [vx, vy, yaw_rate], shape (3,)."""
        return np.array([self.vx, self.vy, self.yaw_rate])

    def pose(self) -> np.ndarray:
        """Global pose [x, y, yaw], shape (3,)."""
        return np.array([self.x, self.y, self.yaw])

    def measurement_values(self) -> dict[str, float]:
        """The eight measured quantities by field name (without any subclass's extras)."""
        return {name: getattr(self, name) for name in MEASUREMENT_FIELDS}


#: Field names of `VehicleMeasurement`, in order.
MEASUREMENT_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(VehicleMeasurement))

"""Disturbances of the plant: what acts on the car besides its commands (docs/plant.md,
"Disturbances").

Body frame at the CG (x forward, y left, yaw counter-clockwise), as ``models.vehicle``.
Every disturbance acts from ``start_s`` (s of the run's time) on:

- ``steer_offset_rad``: the front wheels sit this far from the steering actuator's state
  (a misaligned rack or a wrong sensor zero): true wheel angle = actuator state + offset
  (positive: to the left). STEER_ANGLE reports the actuator state, without the offset, so
  neither the command nor the measurement shows it. (The fault ``[faults.vehicle]
  steer_offset_rad`` of ``hil/faults.py`` adds the offset to the command, and STEER_ANGLE
  shows it.)
- ``bank_angle_rad`` phi: crossfall of the road, positive when the road's left edge is
  lower. Gravity's component in the road plane, m g sin(phi), pulls the car along +y.
  It is taken in body axes (the crossfall across the road the car follows; the car's
  heading error to the road, a few degrees, changes it by its cosine) and acts at the CG.
  Neglected: the smaller normal load m g cos(phi) (-0.18 % at 6 % crossfall) and the
  body's roll on the bank (the plant has no roll degree of freedom; the lateral load
  transfer from the tyres' own lateral forces stays as it is).
- ``crosswind_force_n``: a steady lateral aerodynamic force along +y at the centre of
  pressure ``crosswind_cp_m`` ahead of the CG, so a yaw moment F x_cp; ``gust_force_n``: a
  gust at the same point, 1-cos shaped, F_g (1 - cos(2 pi (t - t_g) / T_g)) / 2 for
  t_g <= t <= t_g + T_g (``gust_start_s``, ``gust_duration_s``), peak F_g at the middle.
  Both in body axes, independent of the car's speed and heading (the force the wind gives
  at the run's speed), at CG height (no roll moment of their own), without aerodynamic
  yaw damping.
- ``yaw_rate_bias_rad_s``: added to the reported YAW_RATE only; the car's motion does not
  change.
- ``pull_wheel`` (FL, FR, RL, RR) and ``pull_stiffness_scale``: that tyre's cornering
  stiffness times the factor (on top of the plant's own per-wheel factor); its peak force
  stays mu Fz. A changed stiffness gives no force at zero slip angle: the tyre pulls only
  while the tyres carry lateral force (in curves, or against another lateral load).

``Disturbances`` is the frozen description (a scenario's ``[disturbances]`` table,
:meth:`Disturbances.from_mapping`); :class:`DisturbanceSchedule` turns it into the
plant's inputs at a time t (:class:`PlantDisturbance`), which ``models.vehicle``'s
derivatives take.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from models.errors import ModelError
from models.vehicle_params import WHEEL_NAMES, VehicleParams

#: Allowed range of each numeric key: (low, high); values outside are refused. Wide
#: enough for any study, narrow enough to catch a unit slip (degrees for radians, percent
#: for a factor, kN for N).
RANGES: dict[str, tuple[float, float]] = {
    "start_s": (0.0, 3600.0),
    "steer_offset_rad": (-0.05, 0.05),
    "bank_angle_rad": (-0.15, 0.15),
    "crosswind_force_n": (-5000.0, 5000.0),
    "crosswind_cp_m": (-3.0, 3.0),
    "gust_force_n": (-5000.0, 5000.0),
    "gust_start_s": (0.0, 3600.0),
    "gust_duration_s": (0.0, 60.0),
    "yaw_rate_bias_rad_s": (-0.1, 0.1),
    "pull_stiffness_scale": (0.1, 2.0),
}
#: Before ``start_s`` by less than this (s) counts as started: the HIL's ticks land on it.
_TIME_TOLERANCE_S = 1e-9


class DisturbanceError(ModelError):
    """A disturbance table has an unknown key, a wrong type or a value out of range."""


@dataclass(frozen=True)
class PlantDisturbance:
    """What the plant's derivative takes at one instant (the same for every row of a batch).

    ``steer_offset_rad``: true front wheel angle minus the actuator state (rad);
    ``lateral_force_n``: external force along body y at the CG (N: wind, gust and the bank's
    gravity component); ``yaw_moment_nm``: external yaw moment (N m); ``stiffness_scale``:
    factor on each tyre's cornering stiffness, order FL, FR, RL, RR.
    """

    steer_offset_rad: float = 0.0
    lateral_force_n: float = 0.0
    yaw_moment_nm: float = 0.0
    stiffness_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class Disturbances:
    """A run's disturbances (see the module docstring); all zero / 1.0 / "" is none."""

    start_s: float = 0.0
    steer_offset_rad: float = 0.0
    bank_angle_rad: float = 0.0
    crosswind_force_n: float = 0.0
    crosswind_cp_m: float = 0.0
    gust_force_n: float = 0.0
    gust_start_s: float = 0.0
    gust_duration_s: float = 0.0
    yaw_rate_bias_rad_s: float = 0.0
    pull_wheel: str = ""
    pull_stiffness_scale: float = 1.0

    def __post_init__(self) -> None:
        _check({f.name: getattr(self, f.name) for f in fields(self)}, "disturbances")

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any], source: object = "disturbances") -> "Disturbances":
        """Parse a ``[disturbances]`` table; every error names ``source``, the key and the value.

        Raises:
            DisturbanceError: not a table, unknown key, wrong type, value out of
                :data:`RANGES`, or an inconsistent pair (a gust without a duration, a
                stiffness factor without a wheel, a gust before ``start_s``).
        """
        if not isinstance(table, Mapping):
            raise DisturbanceError(f"{source}: disturbances = {table!r}: must be a table")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            raise DisturbanceError(f"{source}: unknown key(s) "
                                   f"{', '.join('disturbances.' + k for k in unknown)}; known: "
                                   f"{', '.join(sorted(known))}")
        values: dict[str, Any] = {}
        for key, value in table.items():
            if key == "pull_wheel":
                values[key] = value
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise DisturbanceError(f"{source}: disturbances.{key} = {value!r}: must be a number")
            values[key] = float(value)
        if "pull_wheel" in values and "pull_stiffness_scale" not in values:
            raise DisturbanceError(f"{source}: disturbances.pull_wheel = {values['pull_wheel']!r}: "
                                   "give pull_stiffness_scale too")
        _check({name: values.get(name, getattr(cls, name)) for name in known}, source)
        return cls(**values)

    @property
    def any(self) -> bool:
        """True when something acts on the plant or its measurement."""
        return (any((self.steer_offset_rad, self.bank_angle_rad, self.crosswind_force_n,
                     self.gust_force_n, self.yaw_rate_bias_rad_s))
                or (self.pull_wheel != "" and self.pull_stiffness_scale != 1.0))

    def started(self, time_s: float) -> bool:
        """True from ``start_s`` on."""
        return time_s + _TIME_TOLERANCE_S >= self.start_s

    def gust_force(self, time_s: float) -> float:
        """The gust's lateral force (N) at ``time_s``: 1-cos shaped, 0 outside its window."""
        if self.gust_force_n == 0.0:
            return 0.0
        phase = (time_s - self.gust_start_s) / self.gust_duration_s
        if not 0.0 <= phase <= 1.0:
            return 0.0
        return self.gust_force_n * 0.5 * (1.0 - math.cos(2.0 * math.pi * phase))

    def yaw_rate_bias(self, time_s: float) -> float:
        """What the yaw-rate sensor adds to the true yaw rate at ``time_s`` (rad/s)."""
        return self.yaw_rate_bias_rad_s if self.started(time_s) else 0.0

    def steer_offset(self, time_s: float) -> float:
        """True wheel angle minus the actuator's state at ``time_s`` (rad)."""
        return self.steer_offset_rad if self.started(time_s) else 0.0

    def describe(self) -> str:
        """Short text of what is set (for tables and logs)."""
        parts = [f"{f.name}={getattr(self, f.name):g}" for f in fields(self)
                 if f.name not in ("pull_wheel", "start_s") and getattr(self, f.name) != f.default]
        if self.pull_wheel:
            parts.insert(0, f"pull_wheel={self.pull_wheel}")
        if self.start_s:
            parts.append(f"from {self.start_s:g} s")
        return ", ".join(parts) or "none"


def _check(d: Mapping[str, Any], source: object) -> None:
    """Ranges and the rules between the keys of ``d`` (every field of :class:`Disturbances`
    by name; see :meth:`Disturbances.from_mapping`)."""
    for name, (low, high) in RANGES.items():
        value = d[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise DisturbanceError(f"{source}: disturbances.{name} = {value!r}: must be a finite number")
        if not low <= value <= high:
            raise DisturbanceError(f"{source}: disturbances.{name} = {value!r}: must be in [{low:g}, {high:g}]")
    wheel = d["pull_wheel"]
    if not isinstance(wheel, str) or wheel not in ("", *WHEEL_NAMES):
        raise DisturbanceError(f"{source}: disturbances.pull_wheel = {wheel!r}: must be one of "
                               f"{', '.join(WHEEL_NAMES)}")
    if d["pull_stiffness_scale"] != 1.0 and not wheel:
        raise DisturbanceError(f"{source}: disturbances.pull_stiffness_scale = "
                               f"{d['pull_stiffness_scale']!r}: give pull_wheel (FL, FR, RL or RR) too")
    if d["gust_force_n"] != 0.0 and d["gust_duration_s"] <= 0.0:
        raise DisturbanceError(f"{source}: disturbances.gust_duration_s = {d['gust_duration_s']!r}: "
                               "must be > 0 with a gust_force_n")
    if d["gust_force_n"] != 0.0 and d["gust_start_s"] < d["start_s"]:
        raise DisturbanceError(f"{source}: disturbances.gust_start_s = {d['gust_start_s']!r}: must be "
                               f">= start_s ({d['start_s']:g})")


class DisturbanceSchedule:
    """``disturbances`` on a plant of ``params``: the plant's inputs at any time.

    Args:
        disturbances: what acts.
        params: the plant's parameters (its mass and gravity give the bank's force).
    """

    def __init__(self, disturbances: Disturbances, params: VehicleParams) -> None:
        d = disturbances
        self.disturbances = d
        scale = [1.0, 1.0, 1.0, 1.0]
        if d.pull_wheel:
            scale[WHEEL_NAMES.index(d.pull_wheel)] = d.pull_stiffness_scale
        self._scale = (scale[0], scale[1], scale[2], scale[3])
        self._bank_force = params.mass * params.gravity * math.sin(d.bank_angle_rad)
        self._steady = self._inputs(0.0)

    def _inputs(self, gust: float) -> PlantDisturbance:
        d = self.disturbances
        wind = d.crosswind_force_n + gust
        return PlantDisturbance(steer_offset_rad=d.steer_offset_rad,
                                lateral_force_n=wind + self._bank_force,
                                yaw_moment_nm=wind * d.crosswind_cp_m,
                                stiffness_scale=self._scale)

    def at(self, time_s: float) -> PlantDisturbance | None:
        """The plant's inputs at ``time_s`` (s), None before ``start_s`` (nothing acts)."""
        if not self.disturbances.started(time_s):
            return None
        return self._during(time_s)

    def _during(self, time_s: float) -> PlantDisturbance:
        gust = self.disturbances.gust_force(time_s)
        return self._steady if gust == 0.0 else self._inputs(gust)

    def stages(self, time_s: float, h: float) -> tuple[PlantDisturbance | None, PlantDisturbance | None,
                                                       PlantDisturbance | None]:
        """The inputs of an RK4 step of ``h`` from ``time_s``: at its start, middle and end.
        A step that begins before ``start_s`` has none at all, one that begins at or after
        it all three: the disturbances switch on at a step's boundary, and the state at
        ``start_s`` is the undisturbed one."""
        if not self.disturbances.started(time_s):
            return None, None, None
        return self._during(time_s), self._during(time_s + 0.5 * h), self._during(time_s + h)

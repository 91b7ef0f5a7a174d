"""Vehicle parameters: one frozen dataclass loaded from ``models/vehicle.toml``.

The TOML groups values in sections ([body], [aero], [wheel], [tyre], [actuators],
[simulation]); the dataclass is flat (field name = key name) so overrides read naturally:
``load_vehicle_params(mass=1848.0, mu=0.55)``. Every value is validated on load and a
bad one raises ``VehicleParamsError`` naming the field and the value.

Fields with a default (``cornering_stiffness_rear_scale``) may be left out of a file: a
vehicle file written before they existed loads as the same car.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.errors import VehicleParamsError

#: Default parameter file.
DEFAULT_PARAMS_PATH = Path(__file__).with_name("vehicle.toml")
#: Wheel names in the plant's per-wheel order (front left, front right, rear left, rear right).
WHEEL_NAMES = ("FL", "FR", "RL", "RR")


@dataclass(frozen=True)
class VehicleParams:
    """Parameters of the four-wheel plant (SI units). See vehicle.toml for sources."""

    # [body]
    mass: float
    yaw_inertia: float
    lf: float
    lr: float
    track: float
    cg_height: float
    roll_stiffness_front: float
    # [aero]
    air_density: float
    drag_coefficient: float
    frontal_area: float
    rolling_resistance: float
    # [wheel]
    radius: float
    spin_inertia: float
    # [tyre]
    mu: float
    nominal_load: float
    cornering_stiffness_factor: float
    cornering_stiffness_load_factor: float
    #: Factor on the REAR tyres' cornering stiffness (worn or other rear tyres; issue 20's
    #: changed plant uses 0.8). 1.0 (the default, not in vehicle.toml) is the nominal car:
    #: the stiffness is multiplied by it, and x * 1.0 == x exactly, so the default changes
    #: no result. Keyword-only so that it can have a default among the required fields.
    cornering_stiffness_rear_scale: float = field(default=1.0, kw_only=True)
    shape_lateral: float
    curvature_lateral: float
    slip_stiffness_factor: float
    shape_longitudinal: float
    curvature_longitudinal: float
    relaxation_length: float
    slip_damping_time: float
    # [actuators]
    steer_limit: float
    steer_time_constant: float
    steer_rate_limit: float
    torque_time_constant: float
    max_drive_torque: float
    max_brake_torque: float
    drive_split_front: float
    brake_split_front: float
    brake_fade_speed: float
    # [simulation]
    integration_step: float
    slip_speed_floor: float
    blend_speed_low: float
    blend_speed_high: float
    kinematic_time_constant: float
    load_transfer_time_constant: float
    gravity: float

    @property
    def wheelbase(self) -> float:
        """Front to rear axle distance lf + lr (m)."""
        return self.lf + self.lr

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise VehicleParamsError(f"{f.name}: expected a number, got {value!r}")
            if not math.isfinite(value):
                raise VehicleParamsError(f"{f.name}: must be finite, got {value!r}")
            object.__setattr__(self, f.name, float(value))
            low, high, low_open = _BOUNDS.get(f.name, (0.0, math.inf, True))
            too_low = value <= low if low_open else value < low
            if too_low or value > high:
                bracket = "(" if low_open else "["
                raise VehicleParamsError(
                    f"{f.name}: {value!r} outside {bracket}{low}, {high}]")
        if self.blend_speed_high <= self.blend_speed_low:
            raise VehicleParamsError(
                f"blend_speed_high: {self.blend_speed_high!r} must exceed "
                f"blend_speed_low {self.blend_speed_low!r}")


# (low, high, low bound exclusive); fields not listed must be > 0.
_BOUNDS: dict[str, tuple[float, float, bool]] = {
    "mu": (0.0, 2.0, True),
    "roll_stiffness_front": (0.0, 1.0, False),
    "drive_split_front": (0.0, 1.0, False),
    "brake_split_front": (0.0, 1.0, False),
    "curvature_lateral": (-math.inf, 1.0, False),
    "curvature_longitudinal": (-math.inf, 1.0, False),
    "shape_lateral": (1.0, 2.0, True),
    "shape_longitudinal": (1.0, 2.0, True),
    "steer_limit": (0.0, 0.6, True),
    "integration_step": (0.0, 0.001, True),
    "rolling_resistance": (0.0, 0.1, False),
    "slip_damping_time": (0.0, 1.0, False),
    "cornering_stiffness_rear_scale": (0.0, 2.0, True),
}


def load_vehicle_params(path: str | Path | None = None, **overrides: float) -> VehicleParams:
    """Load parameters from a TOML file (default ``models/vehicle.toml``).

    ``overrides`` replace values by field name, e.g. ``mass=1848.0`` for the +200 kg case.
    Raises ``VehicleParamsError`` for a missing file, unknown or missing keys, bad values.
    """
    source = Path(path) if path is not None else DEFAULT_PARAMS_PATH
    document = read_toml_file(source, "parameter file")
    values: dict[str, Any] = {}
    for section, table in document.items():
        if not isinstance(table, dict):
            raise VehicleParamsError(f"{source}: {section}: expected a [section] table")
        values.update(table)
    return _build(values, overrides, str(source))


def read_toml_file(source: Path, what: str,
                   error: type[VehicleParamsError] = VehicleParamsError) -> dict[str, Any]:
    """The TOML document of the file ``source``; a missing file ("``what`` not found") or
    bad TOML is one ``error`` naming the file."""
    try:
        with open(source, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError as exc:
        raise error(f"{source}: {what} not found") from exc
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{source}: invalid TOML: {exc}") from exc


def _build(values: dict[str, Any], overrides: dict[str, float], source: str) -> VehicleParams:
    names = {f.name for f in dataclasses.fields(VehicleParams)}
    unknown = sorted((set(values) | set(overrides)) - names)
    if unknown:
        raise VehicleParamsError(f"{source}: unknown parameter(s): {', '.join(unknown)}")
    values = {**values, **overrides}
    optional = {f.name for f in dataclasses.fields(VehicleParams) if f.default is not dataclasses.MISSING}
    missing = sorted(names - optional - set(values))
    if missing:
        raise VehicleParamsError(f"{source}: missing parameter(s): {', '.join(missing)}")
    return VehicleParams(**values)


def params_as_dict(params: VehicleParams) -> dict[str, float]:
    """All fields as a plain dict (for manifests and tables)."""
    return dataclasses.asdict(params)

"""Vehicle variants: other cars for the plant, as overrides of ``models/vehicle.toml``.

``models/vehicle_variants.toml`` holds one table per variant (``[van]``): a
``description`` and the changed values in the sections of ``vehicle.toml``
(``[van.body] mass = 2900.0``); every other value is the nominal sedan's. A scenario
selects one with ``[vehicle] variant = "van"`` (``hil.scenario``), so the HIL's plant node
and the closed-loop runner without CAN drive that car; the controllers keep their nominal
models. The road friction ``mu`` is the scenario's and never a variant's.

Checked on load, each error one ``VehicleVariantError`` naming the file, the field and the
value (``models/vehicle_variants.toml: van.body.mass = -1.0: outside (0.0, inf]``): a key
outside its section of ``vehicle.toml``, a value that is not a finite number, a value
outside the plant's bounds (``models.vehicle_params``) or outside the plausible range of
a road car (a unit slip: a mass in tonnes, a length in mm), a yaw inertia whose radius of
gyration is not 0.35-0.60 of the wheelbase, a variant without a description or without
a value.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models.errors import VehicleParamsError
from models.vehicle_params import DEFAULT_PARAMS_PATH, VehicleParams, load_vehicle_params, read_toml_file

#: The shipped variants.
DEFAULT_VARIANTS_PATH = Path(__file__).with_name("vehicle_variants.toml")
#: Fields with a default that ``vehicle.toml`` leaves out, and their section.
_OPTIONAL_FIELD_SECTIONS = {"cornering_stiffness_rear_scale": "tyre"}
#: The road's, set by the scenario ([road] mu), not by a vehicle.
_ROAD_FIELDS = frozenset({"mu"})
#: Plausible values of a road car (unit, low, high): wider than any car we model, narrow
#: enough to catch a mass in tonnes or a length in millimetres. The mass range is the
#: scenario's ``[vehicle] mass_kg`` range.
_PLAUSIBLE: dict[str, tuple[str, float, float]] = {
    "mass": ("kg", 300.0, 5000.0),
    "lf": ("m", 0.5, 3.0),
    "lr": ("m", 0.5, 3.0),
    "track": ("m", 1.0, 2.5),
    "cg_height": ("m", 0.2, 1.5),
    "radius": ("m", 0.2, 0.6),
    "nominal_load": ("N", 1000.0, 20000.0),
}
#: Radius of gyration sqrt(Iz / m) as a share of the wheelbase: passenger cars 0.45-0.50,
#: with margin for compact cars and long vans.
GYRATION_RANGE = (0.35, 0.60)
_NAME = re.compile(r"[a-z][a-z0-9_]*")


class VehicleVariantError(VehicleParamsError):
    """A variants file or one of its values is not usable; the message names the file,
    the field and the value."""


@dataclass(frozen=True)
class VehicleVariant:
    """One variant: its ``overrides`` (field -> value, SI) of the nominal vehicle file
    and the resulting ``params`` (the nominal road friction; a scenario sets its own)."""

    name: str
    description: str
    source: Path
    overrides: Mapping[str, float]
    params: VehicleParams


def field_sections(path: Path = DEFAULT_PARAMS_PATH) -> dict[str, str]:
    """Each vehicle parameter's section in the vehicle file ``path`` (``mass`` -> ``body``),
    the optional fields' included."""
    document = read_toml_file(path, "parameter file")
    sections = {key: section for section, table in document.items() for key in table}
    return {**_OPTIONAL_FIELD_SECTIONS, **sections}


def load_variants(path: str | Path | None = None) -> dict[str, VehicleVariant]:
    """Every variant of the variants file ``path`` (default the shipped one), checked
    (see the module docstring), in file order."""
    source = Path(path) if path is not None else DEFAULT_VARIANTS_PATH
    document = read_toml_file(source, "variants file", VehicleVariantError)
    nominal = load_vehicle_params()
    sections = field_sections()
    return {name: _variant(source, name, table, nominal, sections) for name, table in document.items()}


def variant_names(path: str | Path | None = None) -> tuple[str, ...]:
    """The variants' names, in file order."""
    return tuple(load_variants(path))


def load_variant(name: str, path: str | Path | None = None) -> VehicleVariant:
    """The variant ``name`` of the variants file ``path`` (default the shipped one).

    Raises:
        VehicleVariantError: no such variant (the message lists the known ones), or the
            file or one of its values is bad.
    """
    variants = load_variants(path)
    if name not in variants:
        source = Path(path) if path is not None else DEFAULT_VARIANTS_PATH
        raise VehicleVariantError(f"{source}: unknown vehicle variant {name!r}; "
                                  f"one of {', '.join(variants)}")
    return variants[name]


def _variant(source: Path, name: str, table: Any, nominal: VehicleParams,
             sections: dict[str, str]) -> VehicleVariant:
    if not isinstance(table, dict):
        raise VehicleVariantError(f"{source}: {name} = {table!r}: a variant is a [{name}] table")
    if not _NAME.fullmatch(name):
        raise VehicleVariantError(f"{source}: [{name}]: a variant's name is lower case letters, "
                                  "digits and _, starting with a letter")
    description = table.get("description")
    if not isinstance(description, str) or not description.strip():
        raise VehicleVariantError(f"{source}: {name}.description = {description!r}: "
                                  "must be a non-empty string")
    known_sections = sorted(set(sections.values()))
    overrides: dict[str, float] = {}
    for section, values in table.items():
        if section == "description":
            continue
        if section not in known_sections or not isinstance(values, dict):
            raise VehicleVariantError(f"{source}: {name}.{section}: not a section of "
                                      f"{DEFAULT_PARAMS_PATH.name} ({', '.join(known_sections)})")
        for key, value in values.items():
            overrides[key] = _checked_value(source, f"{name}.{section}.{key}", key, value,
                                            section, sections, nominal)
    if not overrides:
        raise VehicleVariantError(f"{source}: {name}: no value changed (give at least one)")
    try:
        params = dataclasses.replace(nominal, **overrides)
    except VehicleParamsError as exc:  # a relation between fields (blend speeds)
        raise VehicleVariantError(f"{source}: {name}: {exc}") from exc
    _check_gyration(source, name, params)
    return VehicleVariant(name=name, description=description.strip(), source=source,
                          overrides=overrides, params=params)


def _checked_value(source: Path, label: str, key: str, value: Any, section: str,
                   sections: dict[str, str], nominal: VehicleParams) -> float:
    """``value`` of field ``key`` given in ``section`` as a float, or the error."""
    if key in _ROAD_FIELDS:
        raise VehicleVariantError(f"{source}: {label} = {value!r}: the road friction is the "
                                  "scenario's ([road] mu), not a vehicle's")
    if sections.get(key) != section:
        where = f"it belongs in [{sections[key]}]" if key in sections else "unknown vehicle parameter"
        raise VehicleVariantError(f"{source}: {label} = {value!r}: {where}")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise VehicleVariantError(f"{source}: {label} = {value!r}: must be a finite number")
    try:
        dataclasses.replace(nominal, **{key: value})
    except VehicleParamsError as exc:  # the plant's own bounds: "key: value outside (a, b]"
        reason = str(exc).removeprefix(f"{key}: ").removeprefix(f"{value!r} ")
        raise VehicleVariantError(f"{source}: {label} = {value!r}: {reason}") from exc
    if key in _PLAUSIBLE:
        unit, low, high = _PLAUSIBLE[key]
        if not low <= value <= high:
            raise VehicleVariantError(f"{source}: {label} = {value!r}: outside the plausible "
                                      f"[{low:g}, {high:g}] {unit} of a road car (a unit slip?)")
    return float(value)


def _check_gyration(source: Path, name: str, params: VehicleParams) -> None:
    ratio = math.sqrt(params.yaw_inertia / params.mass) / params.wheelbase
    low, high = GYRATION_RANGE
    if not low <= ratio <= high:
        raise VehicleVariantError(
            f"{source}: {name}.body.yaw_inertia = {params.yaw_inertia!r}: radius of gyration "
            f"sqrt(Iz / m) = {ratio:.2f} of the wheelbase, outside [{low}, {high}] "
            f"(mass {params.mass:g} kg, wheelbase {params.wheelbase:g} m)")

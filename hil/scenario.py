"""Scenarios of the double-lane-change study and of the HIL: what road, vehicle, path and
speed request a run uses, loaded from TOML and validated on load.

A scenario file (``hil/scenarios/*.toml``; speeds in km/h as the paper states them,
everything else SI; the attributes of :class:`Scenario` are SI)::

    name = "dlc_high_mu"
    description = "..."
    duration_s = 13.5

    [path]
    id = 1                       # PLANNER_REQ.PATH_ID, 0..255
    file = "../paths/dlc.csv"    # relative to this file, else to the repository

    [road]
    mu = 0.85

    [vehicle]
    mass_offset_kg = 0.0         # or mass_kg = 1648.0 (not both; neither = nominal)
    variant = "van"              # optional: a car of models/vehicle_variants.toml
                                 # (the masses above are then the variant's)
    cornering_stiffness_rear_scale = 0.8  # optional: the rear tyres' cornering stiffness
                                 # times this (on the car's own factor; 1 = as it is)

    [start]                      # plant initial state
    x_m = 0.0
    y_m = 0.0
    yaw_rad = 0.0
    speed_kmh = 35.0

    [speed_profile]              # piecewise-linear target speed, held after the last point
    time_s = [0.0]
    target_speed_kmh = [35.0]

    [faults]                     # optional; kept raw for the fault injector

    [disturbances]               # optional; models.disturbance.Disturbances (docs/plant.md)
    start_s = 0.0                # they act from here on (s)
    steer_offset_rad = 0.01      # wheels off the actuator (and the reported) angle
    bank_angle_rad = 0.03        # road crossfall, + = left edge lower
    crosswind_force_n = 400.0    # along +y (left), at crosswind_cp_m ahead of the CG
    crosswind_cp_m = 0.6
    gust_force_n = 800.0         # 1-cos gust at the same point
    gust_start_s = 2.0
    gust_duration_s = 1.0
    yaw_rate_bias_rad_s = 0.005  # on the reported YAW_RATE only
    pull_wheel = "FR"            # FL, FR, RL, RR: that tyre's cornering stiffness
    pull_stiffness_scale = 0.7   # x this factor

Every error names the file, the field and the offending value.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import PathFileError, ScenarioError
from hil.path_files import read_path_csv

#: Folder of the shipped scenario files.
SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"

_KMH = 1.0 / 3.6  # km/h -> m/s

# Sanity bounds: wide enough for any study we run, narrow enough to catch unit slips
# (a speed in m/s written as km/h, a mass in tonnes, mu as a percentage).
_MU_RANGE = (0.05, 1.5)
_MASS_RANGE_KG = (300.0, 5000.0)
#: Bytes of a scenario file (read no further).
SCENARIO_FILE_MAX_BYTES = 1024 * 1024
_SPEED_RANGE_KMH = (0.0, 200.0)
_DURATION_RANGE_S = (0.025, 3600.0)
#: ``[vehicle] cornering_stiffness_rear_scale``: a changed tyre, not a unit slip (percent).
_REAR_STIFFNESS_SCALE_RANGE = (0.5, 1.5)

_ALLOWED_FIELDS: dict[str, frozenset[str]] = {
    "": frozenset({"name", "description", "duration_s", "path", "road", "vehicle", "start",
                   "speed_profile", "faults", "disturbances"}),
    "path": frozenset({"id", "file"}),
    "road": frozenset({"mu"}),
    "vehicle": frozenset({"mass_kg", "mass_offset_kg", "variant", "cornering_stiffness_rear_scale"}),
    "start": frozenset({"x_m", "y_m", "yaw_rad", "speed_kmh"}),
    "speed_profile": frozenset({"time_s", "target_speed_kmh"}),
}


@dataclass(frozen=True)
class SpeedProfile:
    """Piecewise-linear target speed over time, held constant outside the breakpoints.

    ``times_s`` strictly increasing (s), ``speeds_mps`` the targets there (m/s); both
    tuples of equal length >= 1.
    """

    times_s: tuple[float, ...]
    speeds_mps: tuple[float, ...]

    def target_speed(self, time_s: float) -> float:
        """Target longitudinal speed (m/s) at ``time_s`` (s)."""
        return float(np.interp(time_s, self.times_s, self.speeds_mps))

    def target_speeds(self, times_s: np.ndarray) -> np.ndarray:
        """Target speeds (m/s) at times (s), shape (n,) -> (n,)."""
        return np.interp(np.asarray(times_s, dtype=float), self.times_s, self.speeds_mps)


@dataclass(frozen=True)
class StartState:
    """Initial plant state: pose of the centre of gravity and longitudinal speed."""

    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float


def _no_disturbances() -> Any:
    """``models.disturbance.Disturbances()``: nothing acts (lazy import, as the models)."""
    from models.disturbance import Disturbances

    return Disturbances()


@dataclass(frozen=True)
class Scenario:
    """One closed-loop run's conditions (SI units); load with :meth:`load`.

    ``mass_kg`` None means the plant's nominal mass plus ``mass_offset_kg``.
    ``faults`` is the file's ``[faults]`` table, read-only and uninterpreted here.
    ``disturbances``: the ``[disturbances]`` table as ``models.disturbance.Disturbances``
    (all zero without one); :meth:`vehicle` builds the plant with them.
    ``vehicle_variant``: a variant of ``models/vehicle_variants.toml`` (None: the nominal car).
    """

    name: str
    description: str
    source: Path
    duration_s: float
    path_id: int
    path_file: Path
    mu: float
    mass_kg: float | None
    mass_offset_kg: float
    start: StartState
    speed_profile: SpeedProfile
    faults: Mapping[str, Any] = field(
        default_factory=lambda: types.MappingProxyType({}), hash=False, compare=False
    )
    disturbances: Any = field(default_factory=_no_disturbances)
    vehicle_variant: str | None = None
    #: ``[vehicle] cornering_stiffness_rear_scale``: factor on the car's rear tyres' cornering
    #: stiffness (a changed plant, oversteering below 1; 1.0: the car's own).
    rear_stiffness_scale: float = 1.0

    @classmethod
    def load(cls, file: str | Path) -> "Scenario":
        """Load and validate a scenario TOML file (see the module docstring).

        Raises:
            ScenarioError: unreadable file, TOML syntax, missing/unknown field, wrong type or
                out-of-range value, or an invalid path file.
        """
        file = Path(file)
        from models.input_files import read_bounded

        try:
            raw = tomllib.loads(read_bounded(file, SCENARIO_FILE_MAX_BYTES, ScenarioError).decode("utf-8"))
        except OSError as e:
            raise ScenarioError(f"{file}: cannot read scenario: {e.strerror}") from e
        except UnicodeDecodeError as e:
            raise ScenarioError(f"{file}: not UTF-8 text (byte {e.start}: {e.reason})") from None
        except tomllib.TOMLDecodeError as e:
            raise ScenarioError(f"{file}: invalid TOML: {e}") from e
        return _parse(raw, file)

    def target_speed(self, time_s: float) -> float:
        """Planner's target speed (m/s) at ``time_s``."""
        return self.speed_profile.target_speed(time_s)

    def path_points(self) -> np.ndarray:
        """The reference path, ``[x, y, yaw]`` of shape (n, 3), validated."""
        try:
            return read_path_csv(self.path_file)
        except PathFileError as e:
            raise ScenarioError(f"{self.source}: path.file: {e}") from e

    def plant_mass(self, nominal_mass_kg: float) -> float:
        """Plant mass (kg) for this scenario given the plant's nominal mass."""
        if self.mass_kg is not None:
            return self.mass_kg
        return nominal_mass_kg + self.mass_offset_kg

    def vehicle_params(self) -> Any:
        """The plant's ``models.vehicle_params.VehicleParams`` (the nominal car's or the
        vehicle variant's) with this scenario's mu, mass and rear stiffness factor (lazy
        import: scenario files load without the models package)."""
        from models.vehicle_params import load_vehicle_params

        if self.vehicle_variant is None:
            nominal = load_vehicle_params()
            car = load_vehicle_params(mu=self.mu, mass=self.plant_mass(nominal.mass))
        else:
            from models.vehicle_variants import load_variant

            variant = load_variant(self.vehicle_variant).params
            car = dataclasses.replace(variant, mu=self.mu, mass=self.plant_mass(variant.mass))
        if self.rear_stiffness_scale == 1.0:
            return car
        return dataclasses.replace(car, cornering_stiffness_rear_scale=(
            car.cornering_stiffness_rear_scale * self.rear_stiffness_scale))

    def vehicle(self, params: Any = None) -> Any:
        """The plant of this scenario: ``models.vehicle.FourWheelVehicle`` with ``params``
        (default :meth:`vehicle_params`) and the scenario's disturbances. The HIL plant node
        and the closed-loop runner without CAN both build their plant here."""
        from models.vehicle import FourWheelVehicle

        return FourWheelVehicle(params if params is not None else self.vehicle_params(),
                                disturbances=self.disturbances)


def load_scenario(name_or_file: str | Path) -> Scenario:
    """Load a shipped scenario by name (``"dlc_high_mu"``) or any scenario file by path."""
    candidate = Path(name_or_file)
    if candidate.suffix != ".toml" and not candidate.exists():
        shipped = SCENARIO_DIR / f"{name_or_file}.toml"
        if not shipped.exists():
            raise ScenarioError(
                f"unknown scenario '{name_or_file}': not a file and not one of "
                f"{', '.join(list_scenarios())}"
            )
        candidate = shipped
    return Scenario.load(candidate)


def list_scenarios() -> list[str]:
    """Names of the shipped scenarios (files in ``hil/scenarios``), sorted."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


# --- parsing ---------------------------------------------------------------------------


class _Fields:
    """Typed access to one TOML table with errors naming file, field and value."""

    def __init__(self, file: Path, table: Mapping[str, Any], section: str) -> None:
        self.file = file
        self.table = table
        self.section = section
        unknown = sorted(set(table) - _ALLOWED_FIELDS[section])
        if unknown:
            names = ", ".join(self.name(k) for k in unknown)
            raise ScenarioError(f"{file}: unknown field(s) {names}")

    def name(self, key: str) -> str:
        return f"{self.section}.{key}" if self.section else key

    def error(self, key: str, value: Any, why: str) -> ScenarioError:
        return ScenarioError(f"{self.file}: {self.name(key)} = {value!r}: {why}")

    def has(self, key: str) -> bool:
        return key in self.table

    def text(self, key: str) -> str:
        value = self._get(key)
        if not isinstance(value, str) or not value.strip():
            raise self.error(key, value, "must be a non-empty string")
        return value

    def integer(self, key: str, low: int, high: int) -> int:
        value = self._get(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, value, "must be an integer")
        if not low <= value <= high:
            raise self.error(key, value, f"must be in [{low}, {high}]")
        return value

    def number(self, key: str, low: float = -math.inf, high: float = math.inf,
               *, low_open: bool = False, default: float | None = None) -> float:
        if default is not None and key not in self.table:
            return default
        return self._check_number(key, self._get(key), low, high, low_open)

    def numbers(self, key: str, low: float, high: float) -> tuple[float, ...]:
        value = self._get(key)
        if not isinstance(value, list) or not value:
            raise self.error(key, value, "must be a non-empty array of numbers")
        return tuple(self._check_number(key, item, low, high, False) for item in value)

    def table_of(self, key: str) -> Mapping[str, Any]:
        value = self._get(key)
        if not isinstance(value, dict):
            raise self.error(key, value, "must be a table")
        return value

    def _get(self, key: str) -> Any:
        if key not in self.table:
            raise ScenarioError(f"{self.file}: missing field {self.name(key)}")
        return self.table[key]

    def _check_number(self, key: str, value: Any, low: float, high: float,
                      low_open: bool) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, value, "must be a number")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(key, value, "must be finite")
        too_low = value <= low if low_open else value < low
        if too_low or value > high:
            bracket = "(" if low_open else "["
            raise self.error(key, value, f"must be in {bracket}{low}, {high}]")
        return value


#: The repository's root: a relative ``path.file`` not found beside the scenario file is
#: looked up here, so that a copy of a shipped scenario in another folder can name
#: ``hil/paths/...`` (docs/identification.md section 2).
REPO_ROOT = Path(__file__).resolve().parent.parent


def resolve_path_file(scenario_file: Path, path_text: str) -> Path:
    """The path file ``path_text`` of ``scenario_file``: relative to the scenario's folder,
    else (a relative path only) to the repository's root.

    Raises:
        ScenarioError: a relative path found in neither place; names both places tried.
    """
    beside = (scenario_file.parent / path_text).resolve()
    if beside.exists() or Path(path_text).is_absolute():
        return beside  # an absolute path that does not exist: the reader names it
    in_repository = (REPO_ROOT / path_text).resolve()
    if in_repository.exists():
        return in_repository
    raise ScenarioError(
        f"{scenario_file}: path.file = {path_text!r}: path file not found, neither relative to "
        f"the scenario's folder ({beside}) nor to the repository ({in_repository}); give a path "
        "relative to either, or an absolute one")


def _parse(raw: Mapping[str, Any], file: Path) -> Scenario:
    top = _Fields(file, raw, "")
    name = top.text("name")
    description = top.text("description") if top.has("description") else ""
    duration_s = top.number("duration_s", *_DURATION_RANGE_S)

    path = _Fields(file, top.table_of("path"), "path")
    path_id = path.integer("id", 0, 255)  # PLANNER_REQ.PATH_ID is 8 bits
    path_text = path.text("file")
    path_file = resolve_path_file(file, path_text)
    try:
        read_path_csv(path_file)
    except PathFileError as e:
        raise ScenarioError(f"{file}: path.file = {path_text!r}: {e}") from e

    road = _Fields(file, top.table_of("road"), "road")
    mu = road.number("mu", *_MU_RANGE)

    vehicle = _Fields(file, top.table_of("vehicle") if top.has("vehicle") else {}, "vehicle")
    if vehicle.has("mass_kg") and vehicle.has("mass_offset_kg"):
        raise ScenarioError(
            f"{file}: vehicle.mass_kg and vehicle.mass_offset_kg are exclusive; give one"
        )
    mass_kg = vehicle.number("mass_kg", *_MASS_RANGE_KG) if vehicle.has("mass_kg") else None
    mass_offset_kg = vehicle.number("mass_offset_kg", -1000.0, 2000.0, default=0.0)
    variant = _vehicle_variant(vehicle) if vehicle.has("variant") else None
    rear_stiffness_scale = vehicle.number("cornering_stiffness_rear_scale", *_REAR_STIFFNESS_SCALE_RANGE,
                                          default=1.0)

    start_fields = _Fields(file, top.table_of("start"), "start")
    start = StartState(
        x_m=start_fields.number("x_m"),
        y_m=start_fields.number("y_m"),
        yaw_rad=start_fields.number("yaw_rad", -math.pi, math.pi),
        speed_mps=start_fields.number("speed_kmh", *_SPEED_RANGE_KMH) * _KMH,
    )

    profile_fields = _Fields(file, top.table_of("speed_profile"), "speed_profile")
    times = profile_fields.numbers("time_s", 0.0, _DURATION_RANGE_S[1])
    speeds_kmh = profile_fields.numbers("target_speed_kmh", *_SPEED_RANGE_KMH)
    if len(times) != len(speeds_kmh):
        raise ScenarioError(
            f"{file}: speed_profile.time_s has {len(times)} points but "
            f"speed_profile.target_speed_kmh has {len(speeds_kmh)}"
        )
    if any(later <= earlier for earlier, later in zip(times, times[1:])):
        raise profile_fields.error("time_s", list(times), "must be strictly increasing")
    profile = SpeedProfile(times, tuple(v * _KMH for v in speeds_kmh))

    faults_raw = raw.get("faults", {})
    if not isinstance(faults_raw, dict):
        raise top.error("faults", faults_raw, "must be a table")
    from models.disturbance import DisturbanceError, Disturbances

    try:
        disturbances = Disturbances.from_mapping(raw.get("disturbances", {}), file)
    except DisturbanceError as e:
        raise ScenarioError(str(e)) from e
    return Scenario(
        name=name,
        description=description,
        source=file.resolve(),
        duration_s=duration_s,
        path_id=path_id,
        path_file=path_file,
        mu=mu,
        mass_kg=mass_kg,
        mass_offset_kg=mass_offset_kg,
        start=start,
        speed_profile=profile,
        faults=types.MappingProxyType(copy.deepcopy(faults_raw)),
        disturbances=disturbances,
        vehicle_variant=variant,
        rear_stiffness_scale=rear_stiffness_scale,
    )


def _vehicle_variant(vehicle: _Fields) -> str:
    """``[vehicle] variant``, checked against ``models/vehicle_variants.toml``."""
    from models.vehicle_variants import VehicleVariantError, load_variant

    name = vehicle.text("variant")
    try:
        load_variant(name)
    except VehicleVariantError as e:
        raise vehicle.error("variant", name, str(e)) from e
    return name

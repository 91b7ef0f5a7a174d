"""A campaign grid file's axes and tables, checked (``studies.campaign.grid`` loads the file
and expands the cells): the axes and their defaults, each axis value in its range
(`axis_values`), the ``[speed_profiles]``, ``[faults]`` and ``[disturbances]`` tables, the
``[[exclude]]`` rules (the ``fault_case`` runner's own rules: ``studies.campaign.fault_axes``).

Every error is a `GridError` naming the file and the key.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from hil.errors import HilError
from hil.scenario import _DURATION_RANGE_S, _SPEED_RANGE_KMH

#: A [speed_profiles.NAME] table's bounds: a scenario's [speed_profile] rules.
PROFILE_TIME_MAX_S = _DURATION_RANGE_S[1]
PROFILE_SPEED_RANGE_KMH = _SPEED_RANGE_KMH
#: Every axis, in the order of a cell's fields and of cells.csv.
AXES = ("controller", "scenario", "mu", "speed", "mass_offset_kg", "lag_factor", "fault",
        "model", "seed", "ecu", "disturbance", "runner", "case", "tuning")
REQUIRED_AXES = ("controller", "scenario")
#: Value of an axis the grid does not set: the scenario's own (mu, speed, mass), x1, none.
SCENARIO_VALUE = "scenario"
NO_FAULT = "none"
#: The disturbance axis' value for "nothing added" (a grid without the axis has only it).
NO_DISTURBANCE = "none"
DEFAULT_MODEL = "default"
#: The ECU of a grid without an ``ecu`` axis (and the only one before the axis existed).
DEFAULT_ECU = "python"
#: The runners of the ``runner`` axis: over CAN in lockstep (the default), without CAN,
#: one case of the fault catalogue judged (``studies.campaign.fault_case_cell``), or one
#: model row x seed (below).
HIL_RUNNER = "hil"
CLOSED_LOOP_RUNNER = "closed_loop"
FAULT_CASE_RUNNER = "fault_case"
#: Model rows x seeds, trained or fitted and their open-loop prediction errors measured
#: (Table I; ``studies.campaign.prediction_grid``): a grid of its own schema.
PREDICTION_RUNNER = "prediction"
RUNNERS = (HIL_RUNNER, CLOSED_LOOP_RUNNER, FAULT_CASE_RUNNER, PREDICTION_RUNNER)
#: The case axis' value of a cell that is not a fault case (a grid without the axis and
#: without the ``fault_case`` runner has only it); "none" is a case of the catalogue.
NO_CASE = "-"
#: The tuning axis' value for the tuning file as it is (a grid without the axis has only
#: it); any other value names a ``[tunings.NAME]`` table of overrides.
DEFAULT_TUNING = "file"
#: The controller axis' value for every controller of ``controller.registry``, as the
#: registry has them when the grid loads.
ALL_CONTROLLERS = "all"


class GridError(HilError):
    """A grid file is unreadable or names an unknown axis, value, controller or scenario."""



def axis_values(file: Path, name: str, raw: Any) -> tuple[Any, ...]:
    defaults = {"controller": None, "scenario": None, "mu": SCENARIO_VALUE, "speed": SCENARIO_VALUE,
                "mass_offset_kg": SCENARIO_VALUE, "lag_factor": 1.0, "fault": NO_FAULT,
                "model": DEFAULT_MODEL, "seed": SCENARIO_VALUE, "ecu": DEFAULT_ECU,
                "disturbance": NO_DISTURBANCE, "runner": HIL_RUNNER, "case": NO_CASE,
                "tuning": DEFAULT_TUNING}
    if raw is None:
        return (defaults[name],)
    values = raw if isinstance(raw, list) else [raw]
    if not values:
        raise GridError(f"{file}: axes.{name} is empty")
    if name == "controller" and ALL_CONTROLLERS in values:
        if len(values) > 1:
            raise GridError(f"{file}: axes.controller = {values!r}: {ALL_CONTROLLERS!r} stands alone")
        from controller.registry import ALL_CONTROLLER_NAMES

        values = list(ALL_CONTROLLER_NAMES)
    checked = tuple(axis_value(file, name, v) for v in values)
    if len(set(checked)) != len(checked):
        raise GridError(f"{file}: axes.{name} = {values!r}: repeated value")
    return checked


def axis_value(file: Path, name: str, value: Any) -> Any:
    def bad(why: str) -> GridError:
        return GridError(f"{file}: axes.{name} value {value!r}: {why}")

    number = not isinstance(value, bool) and isinstance(value, (int, float))
    if name == "controller":
        from controller.registry import ALL_CONTROLLER_NAMES

        if value not in ALL_CONTROLLER_NAMES:
            raise bad(f"unknown controller; choose from {', '.join(ALL_CONTROLLER_NAMES)}")
        return value
    if name == "ecu":
        from hil.session import ECU_IMPLEMENTATIONS

        if value not in ECU_IMPLEMENTATIONS:
            raise bad(f"unknown ECU; choose from {', '.join(ECU_IMPLEMENTATIONS)}")
        return value
    if name == "runner":
        if value not in RUNNERS:
            raise bad(f"unknown runner; choose from {', '.join(RUNNERS)}")
        return value
    if name in ("scenario", "fault", "model", "disturbance", "case", "tuning"):
        if not isinstance(value, str) or not value:
            raise bad("must be a non-empty string")
        return value
    if name == "speed" and isinstance(value, str):
        return value
    if name == "seed":
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise bad("must be an integer >= 0")
        return value
    # lag_factor >= 1: a cell adds (factor - 1) x the plant's steering time constant as
    # steer_extra_lag_s, which the plant requires >= 0 (a lag can be added, not removed).
    ranges = {"mu": (0.05, 1.5), "speed": (1.0, 200.0), "mass_offset_kg": (-1000.0, 2000.0),
              "lag_factor": (1.0, 100.0)}
    low, high = ranges[name]
    if not number or not math.isfinite(value) or not low <= value <= high:
        raise bad(f"must be a number in [{low}, {high}]")
    return float(value)



def speed_profiles(file: Path, raw: Any) -> dict[str, tuple[tuple[float, ...], tuple[float, ...]]]:
    if not isinstance(raw, dict):
        raise GridError(f"{file}: speed_profiles must be tables [speed_profiles.NAME]")
    out = {}
    for name, table in raw.items():
        where = f"{file}: speed_profiles.{name}"
        if not isinstance(table, dict) or set(table) != {"time_s", "target_speed_kmh"}:
            raise GridError(f"{where} must have exactly time_s and target_speed_kmh")
        times, speeds = table["time_s"], table["target_speed_kmh"]
        if (not isinstance(times, list) or not isinstance(speeds, list) or not times
                or len(times) != len(speeds)
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in times + speeds)):
            raise GridError(f"{where}: time_s and target_speed_kmh must be arrays of numbers of one length")
        # a scenario's [speed_profile] rules (hil/scenario.py), checked before the first cell
        if not all(math.isfinite(t) and 0.0 <= t <= PROFILE_TIME_MAX_S for t in times):
            raise GridError(f"{where}: time_s = {times!r}: every time must be a number in [0, {PROFILE_TIME_MAX_S}] s")
        if any(later <= earlier for earlier, later in zip(times, times[1:])):
            raise GridError(f"{where}: time_s = {times!r}: must be strictly increasing")
        low, high = PROFILE_SPEED_RANGE_KMH
        if not all(math.isfinite(v) and low <= v <= high for v in speeds):
            raise GridError(f"{where}: target_speed_kmh = {speeds!r}: every speed must be a number in "
                            f"[{low}, {high}] km/h")
        out[name] = (tuple(float(t) for t in times), tuple(float(v) for v in speeds))
    return out


@lru_cache(maxsize=1)
def fault_catalogue() -> dict[str, dict[str, Any]]:
    """The fault catalogue: name -> ``[faults]`` table of each case of ``make faults``
    (``hil.fault_cases.catalogue.campaign_cases``)."""
    from hil.fault_cases.catalogue import campaign_cases

    return {case.name: case.table for case in campaign_cases()}


def grid_faults(file: Path, names: Sequence[str], tables: Mapping[str, Any]) -> dict[str, dict]:
    from hil.faults import FaultSpec, FaultSpecError

    out: dict[str, dict] = {}
    for name in names:
        if name == NO_FAULT:
            out[name] = {}
            continue
        if name in tables:
            table = tables[name]
        elif name in fault_catalogue():
            table = fault_catalogue()[name]
        else:
            raise GridError(f"{file}: axes.fault value {name!r}: not {NO_FAULT!r}, not a "
                            f"[faults.NAME] table of the file and not in the fault catalogue "
                            f"({', '.join(repr(n) for n in fault_catalogue())})")
        try:
            FaultSpec.from_mapping(table, f"{file}: faults {name!r}")
        except FaultSpecError as e:
            raise GridError(str(e)) from e
        out[name] = copy.deepcopy(dict(table))
    return out


def grid_disturbances(file: Path, names: Sequence[str], tables: Any) -> dict[str, dict]:
    """Each disturbance axis value's ``[disturbances]`` table, checked as a scenario's."""
    from models.disturbance import DisturbanceError, Disturbances

    if not isinstance(tables, dict) or not all(isinstance(v, dict) for v in tables.values()):
        raise GridError(f"{file}: [disturbances.NAME] must be tables of a scenario's [disturbances] schema")
    for name, table in tables.items():
        try:
            Disturbances.from_mapping(table, f"{file}: disturbances.{name}")
        except DisturbanceError as e:
            raise GridError(str(e)) from e
    out: dict[str, dict] = {}
    for name in names:
        if name == NO_DISTURBANCE:
            out[name] = {}
        elif name in tables:
            out[name] = copy.deepcopy(tables[name])
        else:
            raise GridError(f"{file}: axes.disturbance value {name!r}: not {NO_DISTURBANCE!r} and not a "
                            f"[disturbances.NAME] table of the file ({', '.join(map(repr, tables)) or 'none defined'})")
    return out


def excludes(file: Path, raw: Any, axes: Mapping[str, tuple]) -> list[dict[str, tuple]]:
    if not isinstance(raw, list) or not all(isinstance(r, dict) for r in raw):
        raise GridError(f"{file}: exclude must be an array of tables ([[exclude]])")
    rules = []
    for i, rule in enumerate(raw):
        unknown = sorted(set(rule) - set(AXES))
        if unknown or not rule:
            raise GridError(f"{file}: exclude[{i}]: unknown axis {', '.join(unknown) or '(empty rule)'}")
        checked = {}
        for name, value in rule.items():
            values = value if isinstance(value, list) else [value]
            checked[name] = tuple(axis_value(file, name, v) for v in values)
            missing = [v for v in checked[name] if v not in axes[name]]
            if missing:
                raise GridError(f"{file}: exclude[{i}].{name} = {missing[0]!r}: not a value of axes.{name}")
        rules.append(checked)
    return rules


def matches(cell: Any, rule: Mapping[str, tuple]) -> bool:
    return all(getattr(cell, name) in values for name, values in rule.items())



"""The ``tuning`` axis of a campaign grid: a cell's controller built from the tuning file
with some of its table's fields replaced (``make tune``'s settings: the grid
``tuning_sweep``, ``studies.tuning_sweep_cells``).

A grid names override tables and a cell picks one by the axis value::

    [axes]
    tuning = ["file", "stiff"]          # "file": the tuning file as it is (the default)

    [tunings.stiff]                     # fields of the cell's controller's tuning table
    q_position = 30.0
    q_yaw = 20.0

    [run]
    tuning_file = "controller/tuning.toml"   # the base file (default: the controller's own)

An override replaces exactly the fields it names in the table of the cell's controller
(``ControllerTuning.for_controller``), as ``controller.tuning.with_fixed_weights`` does: a
scheduled MPC weight also replaces its low-speed twin unless the override names that twin
too (a flat speed schedule). Every other value stays the file's. The controller is then
built by its class's ``from_tuning`` (``controller.registry``), as every study builds it.
Overrides run on the ``closed_loop`` runner only (the C ECU reads its tuning from its data
file, and a ``hil`` cell builds its controller in the ECU).
"""
from __future__ import annotations

import dataclasses
import importlib
import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from studies.campaign.axes import DEFAULT_TUNING, GridError

#: An override as a cell's job carries it: ``((field, value), ...)`` in the table's order.
Override = tuple[tuple[str, float], ...]


def grid_tunings(file: Path, names: Sequence[str], tables: Any) -> dict[str, Override]:
    """Each tuning axis value's override (``"file"``: none), checked for numbers.

    Raises:
        GridError: a ``[tunings.NAME]`` that is no table of numbers, or an axis value
            that names no such table.
    """
    if not isinstance(tables, dict) or not all(isinstance(v, dict) for v in tables.values()):
        raise GridError(f"{file}: [tunings.NAME] must be tables of tuning fields (field = number)")
    out: dict[str, Override] = {}
    for name in names:
        if name == DEFAULT_TUNING:
            out[name] = ()
            continue
        if name not in tables:
            raise GridError(f"{file}: axes.tuning value {name!r}: not {DEFAULT_TUNING!r} and not a "
                            f"[tunings.NAME] table of the file ({', '.join(map(repr, tables)) or 'none defined'})")
        for field, value in tables[name].items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise GridError(f"{file}: tunings.{name}.{field} = {value!r}: must be a finite number")
        out[name] = tuple((field, float(value)) for field, value in tables[name].items())
    return out


def tuning_file(file: Path, raw: Any, root: Path) -> Path | None:
    """``[run] tuning_file`` (relative to the grid file or the repository root), checked by
    loading it; None when the grid does not set it (the controllers' own file)."""
    if raw is None:
        return None
    if not isinstance(raw, str) or not raw:
        raise GridError(f"{file}: run.tuning_file = {raw!r}: must be a path")
    for candidate in (file.parent / raw, root / raw):
        if candidate.is_file():
            from controller.errors import ControllerError
            from controller.tuning import load_tuning

            try:
                load_tuning(candidate)
            except ControllerError as e:
                raise GridError(f"{file}: run.tuning_file: {e}") from e
            return candidate.resolve()
    raise GridError(f"{file}: run.tuning_file = {raw!r}: no such file")


def check_override_fields(file: Path, tuning: Any, controller: str, name: str, override: Override) -> None:
    """Every field of ``override`` exists in ``controller``'s table of ``tuning``."""
    table = tuning.for_controller(controller)
    fields = {f.name for f in dataclasses.fields(table)}
    unknown = [field for field, _ in override if field not in fields]
    if unknown:
        raise GridError(f"{file}: tunings.{name}: {controller}'s table {type(table).__name__} has no "
                        f"field(s) {', '.join(unknown)}")


def tuning_table_attribute(tuning: Any, name: str) -> str:
    """The attribute of ``ControllerTuning`` ``tuning`` that holds controller ``name``'s
    table (the one ``tuning.for_controller(name)`` returns), e.g. ``"eso_dkmpc"``."""
    from hil.errors import StudyError

    table = tuning.for_controller(name)
    for field in dataclasses.fields(tuning):
        if getattr(tuning, field.name) is table:
            return field.name
    raise StudyError(f"controller {name!r}: its tuning table is not a field of {type(tuning).__name__}")


def with_override(tuning: Any, name: str, override: Mapping[str, float] | Override) -> Any:
    """``tuning`` (a ``ControllerTuning``) with controller ``name``'s table's fields of
    ``override`` replaced; every other value unchanged, except that a weight replaces its
    low-speed twin too unless the override names that twin (a flat schedule)."""
    from controller.tuning import with_fixed_weights

    attribute = tuning_table_attribute(tuning, name)
    table = getattr(tuning, attribute)
    return dataclasses.replace(tuning, **{attribute: with_fixed_weights(table, **dict(override))})


def build_controller(name: str, tuning: Any) -> Any:
    """Controller ``name`` of the registry built by its class's ``from_tuning(tuning)``."""
    from controller.registry import CONTROLLERS
    from hil.errors import StudyError

    if name not in CONTROLLERS:
        raise StudyError(f"unknown controller {name!r}; registered: {', '.join(CONTROLLERS)}")
    module_name, class_name = CONTROLLERS[name]
    return getattr(importlib.import_module(module_name), class_name).from_tuning(tuning)


def cell_tuning(tuning_toml: str | None, controller: str, override: Override) -> Any:
    """The ``ControllerTuning`` a cell's controller is built from: the tuning file's text
    (None: ``controller/tuning.toml``) with ``override`` applied (in a worker)."""
    from controller.tuning import load_tuning, parse_tuning

    tuning = load_tuning() if tuning_toml is None else parse_tuning(tomllib.loads(tuning_toml))
    return with_override(tuning, controller, override) if override else tuning

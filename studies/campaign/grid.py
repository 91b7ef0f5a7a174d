"""Campaign grid files: axes expanded as a product, minus exclusions, into cells.

A grid file (TOML; see ``docs/campaign.md`` and ``studies/campaign/grids/``)::

    name = "robustness"
    description = "..."

    [axes]                       # controller and scenario are required, the rest optional
    controller = ["eso-dkmpc", "lmpc"]          # controller.registry names, or ["all"]:
                                                # every name of ALL_CONTROLLER_NAMES
    scenario = ["dlc_high_mu", "my.toml"]       # shipped name, or a file (relative to this file)
    mu = [0.5, 0.85]                            # road friction (replaces the scenario's)
    speed = [30.0, "gentle"]                    # km/h constant (start and target), or the
                                                # name of a [speed_profiles.NAME] table
    mass_offset_kg = [0.0, 300.0]               # replaces the scenario's mass
    lag_factor = [1.0, 3.0]                     # steering time constant x factor
    fault = ["none", "drop 5 %", "my fault"]    # "none", a [faults.NAME] table of this file
                                                # or a case of the fault catalogue (make faults)
    model = ["default", "models/artifacts/dk_paper_nominal.npz"]   # Koopman artefact
    seed = [0, 1]                               # seed of the random faults
    ecu = ["python", "c"]                       # the Python ECU in-process, the C executable
    disturbance = ["none", "wind"]              # "none" or a [disturbances.NAME] table
    runner = ["hil", "closed_loop"]             # over CAN (default), or without CAN; or
                                                # "fault_case" alone (below)
    case = ["drop 5 %", "lost bus"]             # fault_case cells: cases of make faults
    tuning = ["file", "stiff"]                  # closed_loop cells: "file" (the tuning file
                                                # as it is) or a [tunings.NAME] table

    [[exclude]]                  # a cell matching every key of one table is dropped
    controller = "nmpc"
    mu = [0.3, 0.5]              # a value or a list of values

    [run]
    distance_m = 110.0           # cells at a constant speed run this far (+ margin_s);
                                 # or a table by scenario: { dlc_high_mu = 110.0, slalom = 204.0 }
    margin_s = 1.0               # without it a cell keeps its scenario's duration
    keep_trace = false           # true: each row also has the run's e_Y trace (cell.py)
    leave_road_m = 10.0          # closed_loop cells stop, not completed, beyond this |e_Y|
                                 # (m; default studies.campaign.cell.LEAVE_ROAD_M, 2 m)
    tuning_file = "controller/tuning.toml"     # the cells' base tuning file (closed_loop)

    [speed_profiles.gentle]      # as a scenario's [speed_profile]; starts at its first target
    time_s = [0.0, 3.0]
    target_speed_kmh = [40.0, 50.0]

    [faults."my fault"]          # a [faults] table of hil/faults.py
    vehicle = { steer_offset_rad = 0.02 }

    [disturbances.wind]          # a scenario's [disturbances] table (models/disturbance.py)
    crosswind_force_n = 400.0
    crosswind_cp_m = 0.6

    [tunings.stiff]              # fields of the cell's controller's tuning table, replaced
    q_position = 30.0

The ``ecu`` axis (default ``["python"]``) runs a cell on the Python ECU (firmware_sim,
in-process) or on the C ECU executable (``build/firmware/ecu``, ``make firmware``; a
process on a loopback socketcand hub, as ``hil run --ecu c``). A C cell the C ECU cannot
run is left out, not an error (:func:`c_ecu_unavailable`: a controller it does not have,
NMPC and the ablations; a fault sending frame kinds its hub cannot carry), and counted
per reason in ``Grid.c_left_out``.

The ``runner`` axis (default ``["hil"]``) runs a cell over CAN in lockstep
(``hil.session.run_hil``, either ECU) or, with ``closed_loop``, the controller and the plant
in one loop without CAN (``studies.campaign.closed_loop_cell``: the runner of ``make
tables``, for grids too large for the bus). A ``closed_loop`` cell takes no fault (no bus
carries frames there; the lag, mass, friction and disturbance axes act on the plant) and
no C ECU (left out as a C cell the C ECU cannot run).

The ``tuning`` axis (default ``["file"]``; ``studies.campaign.tuning_override``) builds a
``closed_loop`` cell's controller from the tuning file with the fields of one
``[tunings.NAME]`` table replaced: ``make tune``'s settings are such cells of the grid
``tuning_sweep`` (``studies.tuning_sweep_cells``; ``tuning_sweep_smoke`` is its smoke
subset). A cell with the default tuning, no ``tuning_file`` and no ``leave_road_m`` has the
cache key it had before these existed.

The ``fault_case`` runner (``studies.campaign.fault_axes``, ``fault_case_cell``): each cell
is one case of the fault catalogue (the ``case`` axis, default the whole catalogue) with
one controller, judged by ``hil.fault_cases.runs.run_case`` (``make faults``: the grids
``faults`` and ``faults_c``). It stands alone on the runner axis and takes only the
controller, scenario and ecu axes and ``[run] duration_s``; a (case, controller) the case
does not run is left out (``Grid.case_left_out``). The cases that measure the ECU's own
wall-clock behaviour are exclusive cells (``Cell.exclusive``: run alone, after the
others). The axes' values and tables are checked in ``studies.campaign.axes``.

Each cell becomes one scenario TOML (:func:`scenario_document`): the base scenario's file
with the cell's values written in, its ``[faults]`` table holding the fault, the lag and
the seed, its ``[disturbances]`` table the cell's disturbance (replacing the base
scenario's own; "none" keeps the base scenario's, as the fault axis does). ``python -m hil run --scenario THAT.toml --controller NAME --faults`` is the
same run as the cell's (tests/test_campaign.py checks it); a C cell's adds ``--ecu c``.

Every error is raised before any cell runs and names the file and the key.
"""
from __future__ import annotations

import copy
import itertools
import math
import tomllib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from models.input_files import read_bounded
from studies.campaign.axes import (  # noqa: F401 - the axes' names, where they always were
    ALL_CONTROLLERS, AXES, CLOSED_LOOP_RUNNER, DEFAULT_ECU, DEFAULT_MODEL, DEFAULT_TUNING, FAULT_CASE_RUNNER,
    HIL_RUNNER, NO_CASE, NO_DISTURBANCE, NO_FAULT, PROFILE_SPEED_RANGE_KMH, PROFILE_TIME_MAX_S,
    PREDICTION_RUNNER, REQUIRED_AXES, RUNNERS, SCENARIO_VALUE, GridError, axis_values, excludes, fault_catalogue,
    grid_disturbances, grid_faults, matches, speed_profiles)
from studies.campaign.fault_axes import check_fault_case_axes, fault_case_left_out
from studies.campaign.toml_text import to_toml  # noqa: F401 - the cells' scenario text
from studies.campaign.tuning_override import Override, check_override_fields, grid_tunings, tuning_file

if TYPE_CHECKING:
    from studies.campaign.prediction_grid import PredictionGrid

ROOT = Path(__file__).resolve().parent.parent.parent
#: Bytes of a grid file (read no further).
GRID_FILE_MAX_BYTES = 1024 * 1024
GRID_DIR = Path(__file__).resolve().parent / "grids"
#: Controllers that run a Koopman artefact (the only ones the model axis changes).
KOOPMAN_CONTROLLERS = ("eso-dkmpc", "dkmpc")
#: Path the MPC horizons need beyond a run's last position (m): 30 steps at 25 ms, 70 km/h.
HORIZON_ROOM_M = 15.0
CONTROL_PERIOD_S = 0.025
_TOP_KEYS = {"name", "description", "axes", "exclude", "run", "speed_profiles", "faults", "disturbances",
             "tunings"}
_RUN_KEYS = {"distance_m", "margin_s", "keep_trace", "duration_s", "tuning_file", "leave_road_m"}
_KMH = 1.0 / 3.6

@dataclass(frozen=True)
class Cell:
    """One run of a campaign: a value on every axis (see the module docstring)."""

    controller: str
    scenario: str
    mu: float | str = SCENARIO_VALUE
    speed: float | str = SCENARIO_VALUE
    mass_offset_kg: float | str = SCENARIO_VALUE
    lag_factor: float = 1.0
    fault: str = NO_FAULT
    model: str = DEFAULT_MODEL
    seed: int | str = SCENARIO_VALUE
    ecu: str = DEFAULT_ECU
    disturbance: str = NO_DISTURBANCE
    runner: str = HIL_RUNNER
    case: str = NO_CASE
    tuning: str = DEFAULT_TUNING

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def label(self) -> str:
        """Short text for errors and logs."""
        return ", ".join(f"{k}={v}" for k, v in self.as_dict().items()
                         if v not in (SCENARIO_VALUE, NO_FAULT, DEFAULT_MODEL) and
                         not (k == "lag_factor" and v == 1.0) and not (k == "ecu" and v == DEFAULT_ECU)
                         and not (k == "runner" and v == HIL_RUNNER) and k not in ("case", "tuning")
                         ) + (f", case={self.case}" if self.case != NO_CASE else "") + (
                             f", tuning={self.tuning}" if self.tuning != DEFAULT_TUNING else "")

    @property
    def exclusive(self) -> bool:
        """The cell must run alone, in the driver, after every other cell: it measures the
        ECU's own wall-clock behaviour, so no other run may compete with it for the cores
        (a fault case with an ECU-level fault: ``studies.campaign.fault_case_cell``)."""
        if self.runner != FAULT_CASE_RUNNER:
            return False
        from studies.campaign.fault_case_cell import case_is_exclusive

        return case_is_exclusive(self.case)


@dataclass(frozen=True)
class Grid:
    """A loaded grid: its cells in product order (exclusions applied) and what the cells
    need to become scenarios."""

    name: str
    description: str
    source: Path
    cells: tuple[Cell, ...]
    scenario_files: Mapping[str, Path]
    speed_profiles: Mapping[str, tuple[tuple[float, ...], tuple[float, ...]]]
    faults: Mapping[str, Mapping[str, Any]]
    #: ``[run] distance_m``: one distance (m) for every scenario, or one per scenario name.
    distance_m: float | Mapping[str, float] | None
    margin_s: float
    excluded: int
    not_applicable: int
    #: C cells left out because the C ECU cannot run them: reason -> count.
    c_left_out: Mapping[str, int] = field(default_factory=dict)
    #: disturbance axis value -> its ``[disturbances]`` table ("none": empty).
    disturbances: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    #: ``[run] keep_trace``: the cells' rows carry their e_Y trace.
    keep_trace: bool = False
    #: ``[run] duration_s``: the ``fault_case`` cells' scenario duration (None: the scenario's).
    duration_s: float | None = None
    #: fault_case cells left out: a controller the case does not run.
    case_left_out: int = 0
    #: tuning axis value -> its override (``[tunings.NAME]``; "file": none).
    tunings: Mapping[str, Override] = field(default_factory=dict)
    #: ``[run] tuning_file``: the base tuning file of every cell (None: the controllers' own).
    tuning_file: Path | None = None
    #: ``[run] leave_road_m``: the ``closed_loop`` cells' |e_Y| limit (m) beyond which a
    #: run stops, not completed (None: ``studies.campaign.cell.LEAVE_ROAD_M``).
    leave_road_m: float | None = None

    def scenario_document(self, cell: Cell) -> dict[str, Any]:
        """The cell's scenario as a TOML document (dict); ``path.file`` is absolute."""
        return scenario_document(self, cell)

    def distance_for(self, scenario: str) -> float | None:
        """``[run] distance_m`` of the cells of ``scenario`` (None: their scenario's duration)."""
        if isinstance(self.distance_m, Mapping):
            return self.distance_m.get(scenario)
        return self.distance_m


# ---------------------------------------------------------------------------- loading

def load_grid(file: str | Path) -> Grid | PredictionGrid:
    """Read, validate and expand a grid file (a ``prediction`` grid, Table I's model rows x
    seeds: ``studies.campaign.prediction_grid``).

    Raises:
        GridError: unreadable file, unknown key, axis, value, controller, scenario, fault,
            model artefact or speed profile, or a path too short for a cell.
    """
    file = Path(file)
    if not file.is_file() and (GRID_DIR / f"{file}.toml").is_file():
        file = GRID_DIR / f"{file}.toml"
    try:
        raw = tomllib.loads(read_bounded(file, GRID_FILE_MAX_BYTES, GridError).decode("utf-8"))
    except OSError as e:
        raise GridError(f"{file}: cannot read grid: {e.strerror}") from e
    except UnicodeDecodeError as e:
        raise GridError(f"{file}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except tomllib.TOMLDecodeError as e:
        raise GridError(f"{file}: invalid TOML: {e}") from e
    runners = raw.get("axes", {}).get("runner") if isinstance(raw.get("axes"), dict) else None
    if PREDICTION_RUNNER in (runners if isinstance(runners, list) else [runners]):
        # its own schema (Table I's model rows x seeds); the trainer (torch) is imported only for it
        from studies.campaign.prediction_grid import load_prediction_grid

        return load_prediction_grid(file, raw, ROOT)
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise GridError(f"{file}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(_TOP_KEYS))}")
    axes_raw = raw.get("axes")
    if not isinstance(axes_raw, dict):
        raise GridError(f"{file}: missing table [axes]")
    unknown = sorted(set(axes_raw) - set(AXES))
    if unknown:
        raise GridError(f"{file}: unknown axis {', '.join(unknown)}; axes: {', '.join(AXES)}")
    for name in REQUIRED_AXES:
        if name not in axes_raw:
            raise GridError(f"{file}: axes.{name} is required")
    profiles = speed_profiles(file, raw.get("speed_profiles", {}))
    tables = raw.get("faults", {})
    if not isinstance(tables, dict) or not all(isinstance(v, dict) for v in tables.values()):
        raise GridError(f"{file}: [faults.NAME] must be tables of hil/faults.py's [faults] schema")
    axes = {name: axis_values(file, name, axes_raw.get(name)) for name in AXES}
    scenario_files = {name: _scenario_file(file, name) for name in axes["scenario"]}
    faults = grid_faults(file, axes["fault"], raw.get("faults", {}))
    disturbances = grid_disturbances(file, axes["disturbance"], raw.get("disturbances", {}))
    for name, value in (("speed", v) for v in axes["speed"]):
        if isinstance(value, str) and value not in (SCENARIO_VALUE, *profiles):
            raise GridError(f"{file}: axes.{name} = {value!r}: not a number (km/h) and not a "
                            f"[speed_profiles.NAME] table ({', '.join(profiles) or 'none defined'})")
    for model in axes["model"]:
        if model != DEFAULT_MODEL:
            _model_file(file, model)
    run = raw.get("run", {})
    if not isinstance(run, dict) or set(run) - _RUN_KEYS:
        raise GridError(f"{file}: [run] takes only {', '.join(sorted(_RUN_KEYS))}")
    distance = run.get("distance_m")
    margin = run.get("margin_s", 1.0)
    numbers = [("distance_m", distance), ("margin_s", margin)]
    if isinstance(distance, dict):
        unknown = sorted(set(distance) - set(axes["scenario"]))
        if unknown:
            raise GridError(f"{file}: run.distance_m.{unknown[0]}: not a value of axes.scenario "
                            f"({', '.join(axes['scenario'])})")
        numbers = [(f"distance_m.{name}", value) for name, value in distance.items()] + numbers[1:]
    for key, value in numbers:
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or not 0 <= value < 1e5):
            raise GridError(f"{file}: run.{key} = {value!r}: must be a number >= 0")
    if CLOSED_LOOP_RUNNER in axes["runner"] and any(name != NO_FAULT for name in axes["fault"]):
        raise GridError(f"{file}: axes.fault with runner {CLOSED_LOOP_RUNNER!r}: that runner has no bus "
                        f"to inject faults on; run faults with runner {HIL_RUNNER!r}")
    leave_road = run.get("leave_road_m")
    if leave_road is not None and (isinstance(leave_road, bool) or not isinstance(leave_road, (int, float))
                                   or not 0 < leave_road < 1e3):
        raise GridError(f"{file}: run.leave_road_m = {leave_road!r}: must be a number in (0, 1000) m")
    tunings = grid_tunings(file, axes["tuning"], raw.get("tunings", {}))
    if any(name != DEFAULT_TUNING for name in axes["tuning"]) and set(axes["runner"]) != {CLOSED_LOOP_RUNNER}:
        raise GridError(f"{file}: axes.tuning with runner {axes['runner']}: tuning overrides run on the "
                        f"{CLOSED_LOOP_RUNNER!r} runner only (the ECUs build their own controllers)")
    base_tuning = tuning_file(file, run.get("tuning_file"), ROOT)
    keep_trace = run.get("keep_trace", False)
    if not isinstance(keep_trace, bool):
        raise GridError(f"{file}: run.keep_trace = {keep_trace!r}: must be true or false")
    check_fault_case_axes(file, axes, axes_raw, run)   # the whole catalogue when no case axis
    rules = excludes(file, raw.get("exclude", []), axes)

    cells, excluded, not_applicable, case_left_out = [], 0, 0, 0
    c_left_out: dict[str, int] = {}
    for values in itertools.product(*(axes[name] for name in AXES)):
        cell = Cell(*values)
        if any(matches(cell, rule) for rule in rules):
            excluded += 1
        elif fault_case_left_out(cell):
            case_left_out += 1  # a controller the case does not run
        elif cell.model != DEFAULT_MODEL and cell.controller not in KOOPMAN_CONTROLLERS:
            not_applicable += 1  # the same run as the default model's
        elif (reason := c_ecu_unavailable(cell, faults)) is not None:
            c_left_out[reason] = c_left_out.get(reason, 0) + 1
        else:
            cells.append(cell)
    grid = Grid(name=str(raw.get("name", file.stem)), description=str(raw.get("description", "")),
                source=file.resolve(), cells=tuple(cells), scenario_files=scenario_files,
                speed_profiles=profiles, faults=faults,
                distance_m=_distances(distance), margin_s=float(margin),
                excluded=excluded, not_applicable=not_applicable, c_left_out=c_left_out,
                disturbances=disturbances, keep_trace=keep_trace,
                duration_s=None if run.get("duration_s") is None else float(run["duration_s"]),
                case_left_out=case_left_out, tunings=tunings, tuning_file=base_tuning,
                leave_road_m=None if leave_road is None else float(leave_road))
    if not cells:
        left_out = "".join(f"; {n} C cells left out: {why}" for why, n in c_left_out.items())
        raise GridError(f"{file}: no cell left after the exclusions{left_out}")
    for cell in cells:  # every scenario builds, every path is long enough: before any run
        scenario_document(grid, cell)
    if any(override for override in tunings.values()):
        from controller.tuning import load_tuning

        base = load_tuning(base_tuning)
        for cell in {(c.controller, c.tuning): c for c in cells}.values():
            check_override_fields(file, base, cell.controller, cell.tuning, tunings[cell.tuning])
    return grid


def _distances(raw: Any) -> float | dict[str, float] | None:
    """``[run] distance_m`` as floats (checked by :func:`load_grid`)."""
    if raw is None:
        return None
    if isinstance(raw, dict):
        return {name: float(value) for name, value in raw.items()}
    return float(raw)


def c_ecu_unavailable(cell: Cell, faults: Mapping[str, Mapping[str, Any]]) -> str | None:
    """Why the C ECU cannot run ``cell`` (the reason it is left out of the grid), or None
    when it can (and for every Python cell). ``faults``: fault name -> ``[faults]`` table.

    The rule: the C ECU has the controllers ``hil.session.C_ECU_CONTROLLERS`` (NMPC and the
    ablations are Python only), and its loopback socketcand hub cannot carry FD, remote or
    error frames (``hil.fault_cases.c_ecu.c_not_applicable``: a fault sending such
    look-alikes would be another fault there).
    """
    if cell.ecu != "c" or cell.runner == FAULT_CASE_RUNNER:
        return None  # a case the C ECU cannot take is run and reported not applicable
    if cell.runner == CLOSED_LOOP_RUNNER:
        return f"the {CLOSED_LOOP_RUNNER} runner has no bus for the C ECU"
    from hil.session import C_ECU_CONTROLLERS

    if cell.controller not in C_ECU_CONTROLLERS:
        return f"the C ECU has no {cell.controller} (Python only)"
    from hil.fault_cases.c_ecu import c_not_applicable
    from hil.fault_cases.catalogue import FaultCase

    if c_not_applicable(FaultCase(cell.fault, "bus", dict(faults[cell.fault]), ())) is not None:
        return (f"fault {cell.fault!r}: FD / remote / error frames, which the C ECU's loopback "
                "socketcand hub cannot carry")
    return None


def _scenario_file(file: Path, name: str) -> Path:
    from hil.scenario import SCENARIO_DIR, list_scenarios

    for candidate in ((file.parent / name), ROOT / name, SCENARIO_DIR / f"{name}.toml"):
        if candidate.suffix == ".toml" and candidate.is_file():
            return candidate.resolve()
    raise GridError(f"{file}: axes.scenario value {name!r}: not a scenario file and not one of "
                    f"{', '.join(list_scenarios())}")


def _model_file(file: Path, model: str) -> Path:
    for candidate in (file.parent / model, ROOT / model):
        if candidate.suffix == ".npz" and candidate.is_file():
            if not candidate.resolve().is_relative_to(ROOT):   # the cells name it from the checkout
                raise GridError(f"{file}: axes.model value {model!r}: {candidate.resolve()} is outside the "
                                f"repository {ROOT}; copy the artefact (.npz and .json) into it")
            return candidate.resolve()
    raise GridError(f"{file}: axes.model value {model!r}: not {DEFAULT_MODEL!r} and not a "
                    "Koopman artefact (.npz with its .json)")


def model_file(grid: Grid, model: str) -> Path | None:
    """The artefact of a model axis value (None: the controllers' default)."""
    return None if model == DEFAULT_MODEL else _model_file(grid.source, model)


# ---------------------------------------------------------------------------- cell -> scenario

def scenario_document(grid: Grid, cell: Cell) -> dict[str, Any]:
    """The cell's scenario TOML document: the base scenario with the cell's mu, speed, mass,
    duration, a ``[faults]`` table (fault, lag, seed) and its disturbance's
    ``[disturbances]`` table. ``path.file`` is absolute.

    Raises:
        GridError: the path ends before the run's last position plus the horizons.
    """
    from hil.scenario import Scenario

    base_file = grid.scenario_files[cell.scenario]
    document = tomllib.loads(base_file.read_text(encoding="utf-8"))
    base = Scenario.load(base_file)
    document["name"] = f"{base.name}-cell"
    document["description"] = f"campaign {grid.name} cell of {base.name}: {cell.label}"
    document["path"]["file"] = str(base.path_file)
    if cell.mu != SCENARIO_VALUE:
        document.setdefault("road", {})["mu"] = cell.mu
    if cell.mass_offset_kg != SCENARIO_VALUE:
        document["vehicle"] = {"mass_offset_kg": cell.mass_offset_kg}
    start_speed_kmh = base.start.speed_mps * 3.6
    if cell.speed != SCENARIO_VALUE:
        if isinstance(cell.speed, str):
            times, speeds = grid.speed_profiles[cell.speed]
        else:
            times, speeds = (0.0,), (cell.speed,)
        document["speed_profile"] = {"time_s": list(times), "target_speed_kmh": list(speeds)}
        document["start"]["speed_kmh"] = speeds[0]
        start_speed_kmh = speeds[0]
        distance = grid.distance_for(cell.scenario)
        if distance is not None and len(speeds) == 1:
            seconds = distance / (speeds[0] * _KMH) + grid.margin_s
            document["duration_s"] = round(math.ceil(seconds / CONTROL_PERIOD_S - 1e-9)
                                           * CONTROL_PERIOD_S, 3)
    faults = copy.deepcopy(dict(grid.faults[cell.fault]))
    if cell.lag_factor != 1.0:
        from models.vehicle_params import load_vehicle_params

        extra = (cell.lag_factor - 1.0) * load_vehicle_params().steer_time_constant
        vehicle = dict(faults.get("vehicle", {}))
        vehicle["steer_extra_lag_s"] = vehicle.get("steer_extra_lag_s", 0.0) + extra
        faults["vehicle"] = vehicle
    if cell.seed != SCENARIO_VALUE:
        faults["seed"] = cell.seed
    if faults or "faults" in document:
        document["faults"] = {**document.get("faults", {}), **faults}
    if cell.disturbance != NO_DISTURBANCE:
        document["disturbances"] = copy.deepcopy(dict(grid.disturbances[cell.disturbance]))
    _check_path_length(grid, cell, document, base, start_speed_kmh)
    return document


def effective_values(document: Mapping[str, Any], cell: Cell) -> dict[str, Any]:
    """The cell's axis values with the scenario's own in place of ``"scenario"``: mu, the
    constant speed (km/h; a profile keeps its name, the scenario's own is ``profile``), the
    mass offset (kg) and the faults' seed."""
    values = cell.as_dict()
    if cell.mu == SCENARIO_VALUE:
        values["mu"] = float(document["road"]["mu"])
    if cell.speed == SCENARIO_VALUE:
        speeds = document["speed_profile"]["target_speed_kmh"]
        values["speed"] = float(speeds[0]) if len(speeds) == 1 else "profile"
    if cell.mass_offset_kg == SCENARIO_VALUE:
        values["mass_offset_kg"] = float(document.get("vehicle", {}).get("mass_offset_kg", 0.0))
    if cell.seed == SCENARIO_VALUE:
        values["seed"] = int(document.get("faults", {}).get("seed", 0))
    return values


def _check_path_length(grid: Grid, cell: Cell, document: Mapping[str, Any], base: Any,
                       start_speed_kmh: float) -> None:
    profile = document["speed_profile"]["target_speed_kmh"]
    top_speed = max([start_speed_kmh, *profile]) * _KMH
    reach = base.start.x_m + top_speed * float(document["duration_s"]) + HORIZON_ROOM_M
    path_end = float(base.path_points()[-1, 0])
    if reach > path_end + 1e-6 and cell.speed != SCENARIO_VALUE:
        raise GridError(f"{grid.source}: cell {cell.label}: the run may reach X = {reach:.0f} m "
                        f"with its horizon, the path ends at {path_end:.0f} m "
                        "(set [run] distance_m or lower the speed)")

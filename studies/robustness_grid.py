"""Robustness grid on our plant (issue 14 item 7, ``make robustness``): every controller in
closed loop with the four-wheel plant (``studies.closed_loop``, no CAN) over a grid of
road friction, speed, load, steering lag and manoeuvre.

The grid (:func:`grid_cells`, 4 x 3 x 2 x 2 x 2 = 96 cells per controller):

- ``mu`` 0.3 / 0.5 / 0.85 / 1.0 (the plant's road friction);
- ``speed_kmh`` 30 / 50 / 70: constant target speed, the run starts at that speed;
- ``mass_offset_kg`` +0 / +300 kg on the plant's nominal mass (the yaw inertia, the axle
  positions and the tyres stay the nominal ones, as in the scenarios' ``mass_offset_kg``);
- ``lag_factor`` x1 / x3: the plant's steering actuator time constant
  ``steer_time_constant`` (``models/vehicle.toml``, 30 ms) multiplied; the actuator's rate
  limit ``steer_rate_limit`` stays, so the factor changes the lag alone;
- ``manoeuvre``: the double lane change (``hil/paths/dlc.csv``) and the slalom
  (``hil/paths/slalom.csv``, ``hil.path_files.SLALOM``: 6 cones 24 m apart, passed 1 m
  to the side).

Each run starts on the path at X = 0 and lasts (end of the course in X + ``SETTLE_M``) /
speed + ``MARGIN_S``: the course, a short straight to settle, and a margin
(:func:`run_duration_s`). A run that leaves the road (|e_Y| > ``LEAVE_ROAD_M`` = 2 m: the
runner stops it there) or that the runner stops for any other reason (non-finite or
diverged plant, an exception in ``controller.step``) counts as not completed; one whose
controller or plant cannot even be built is recorded with its ``error``. The grid goes on
either way.

The runs are Ray tasks on the campaigns' executors (``studies.campaign.executors``): a
local Ray with ``--workers`` CPUs (default 2, one BLAS thread each), or the cluster at
``--address``; ``--workers 1`` runs them in this process. Each run's result is cached as
JSON in ``--cache`` (default ``build/robustness/``) under a hash of the cell, the
controller, the run's settings, the plant's parameters and the digests of the tuning
file, the model artefacts, the path files and the source of the controller and the runner
(:func:`run_key`), so a re-run resumes where it stopped and recomputes exactly the runs
whose inputs changed. The controllers are built from a copy of the tuning file taken when
the grid starts (a tuning sweep may rewrite ``controller/tuning.toml`` meanwhile); if
another input (an artefact, a path, a source file) changes while the grid runs, the runs
of that call are dropped from the cache and the grid stops with an error.

Writes to ``--out`` (default ``results/``):

- ``robustness.md``: (a) per controller the cells completed, the mean / median e_Y RMSE
  over the cells that every controller completed and on how many of those it has the
  lowest e_Y RMSE; (b) e_Y RMSE by mu x speed per controller (mean over the other axes,
  those cells only); (c) the measured ranking; (d) completed runs by mu x speed;
- ``robustness.csv``: one row per run (:data:`CSV_FIELDS`);
- ``robustness.png``: heat maps of e_Y RMSE over mu x speed per controller, double lane
  change and slalom at nominal mass and lag.

Usage: ``python -m studies.robustness_grid [--controllers ...] [--manoeuvres ...]
[--workers N] [--address ADDR] [--out DIR] [--cache DIR] [--no-cache] [--quick] [--no-progress] [--debug]``.
``--quick`` runs :data:`QUICK_CONTROLLERS` on :data:`QUICK_CELLS` (2 x 2 runs) into
``build/robustness-smoke/`` unless ``--out`` says otherwise. Exit status: 0 when the grid
ran (whatever each run's outcome), 1 when it could not (bad inputs, unwritable output),
2 for bad arguments.
"""
from __future__ import annotations

import os

# One BLAS thread per process, before numpy is imported here or in a spawned worker: the
# matrices are tiny and the workers already use the cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import dataclasses  # noqa: E402
import functools  # noqa: E402
import hashlib  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from collections.abc import Callable, Iterator, Mapping, Sequence  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from controller.registry import ABLATION_NAMES, ALL_CONTROLLER_NAMES, CONTROLLER_NAMES, CONTROLLERS  # noqa: E402
from hil.errors import HilError, StudyError  # noqa: E402
from hil.path_files import DLC_PATH_FILE, SLALOM, SLALOM_PATH_FILE, read_path_csv  # noqa: E402
from hil.scenario import Scenario, SpeedProfile, StartState  # noqa: E402
from studies.closed_loop import CONTROL_PERIOD_MS, run_closed_loop  # noqa: E402
from studies.machine import machine_description  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

#: The grid's axes.
MUS = (0.3, 0.5, 0.85, 1.0)
SPEEDS_KMH = (30.0, 50.0, 70.0)
MASS_OFFSETS_KG = (0.0, 300.0)
LAG_FACTORS = (1.0, 3.0)
#: Every controller of the study: the paper's four, then the ablations.
GRID_CONTROLLERS = CONTROLLER_NAMES + ABLATION_NAMES

#: A run that gets farther than this from the path (m) has left the road: not completed.
LEAVE_ROAD_M = 2.0
#: Straight driven after the end of the course (m), to see the controller settle.
SETTLE_M = 20.0
#: Time added to every run (s).
MARGIN_S = 1.0
#: Path the MPC horizons need beyond the last position of a run (m): 30 steps of 25 ms at
#: 70 km/h is 14.6 m.
HORIZON_ROOM_M = 15.0

#: Bump when what a run computes changes in a way the key's other parts do not show.
CACHE_VERSION = 1
#: Default folders.
DEFAULT_CACHE = ROOT / "build" / "robustness"
QUICK_OUT = ROOT / "build" / "robustness-smoke"

#: One row of ``robustness.csv`` per run, in this order.
CSV_FIELDS = ("controller", "manoeuvre", "mu", "speed_kmh", "mass_offset_kg", "lag_factor",
              "completed", "e_y_rmse", "e_y_max", "heading_rmse", "error")

#: Builds a controller from its registry name (``controller.registry.create_controller``
#: by default); a module-level function, so that it reaches spawned workers.
ControllerFactory = Callable[[str], Any]

_KMH = 1.0 / 3.6


@dataclass(frozen=True)
class Manoeuvre:
    """A course of the grid: its path file and where the course ends in X (m)."""

    name: str
    title: str
    path_file: Path
    path_id: int
    course_end_x_m: float


#: The manoeuvres, by name. The double lane change's second tanh has settled (Y within 1 mm
#: of its final value) by X = 90 m; the slalom is back on Y = 0 one cone spacing after the
#: last cone.
MANOEUVRES: dict[str, Manoeuvre] = {
    "dlc": Manoeuvre("dlc", "double lane change", DLC_PATH_FILE, 1, 90.0),
    "slalom": Manoeuvre("slalom", f"slalom, {SLALOM.cone_count} cones "
                        f"{SLALOM.cone_spacing_m:g} m apart", SLALOM_PATH_FILE, 2, SLALOM.exit_x_m),
}


@dataclass(frozen=True)
class Cell:
    """One set of conditions of the grid (a run per controller)."""

    manoeuvre: str
    mu: float
    speed_kmh: float
    mass_offset_kg: float
    lag_factor: float

    @property
    def name(self) -> str:
        """File-name-safe identifier: ``dlc_mu0.85_50kmh_+0kg_lag1``."""
        return (f"{self.manoeuvre}_mu{self.mu:g}_{self.speed_kmh:g}kmh_"
                f"{self.mass_offset_kg:+g}kg_lag{self.lag_factor:g}")

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: ``--quick``: two fast controllers on two cells that touch every axis.
QUICK_CONTROLLERS = ("lmpc", "dkmpc")
QUICK_CELLS = (Cell("dlc", 0.85, 50.0, 0.0, 1.0), Cell("slalom", 0.5, 50.0, 300.0, 3.0))


def grid_cells(manoeuvres: Sequence[str] = tuple(MANOEUVRES)) -> list[Cell]:
    """Every cell of the grid for ``manoeuvres``: 48 per manoeuvre, manoeuvre-major."""
    for name in manoeuvres:
        if name not in MANOEUVRES:
            raise StudyError(f"unknown manoeuvre {name!r}; choose from {', '.join(MANOEUVRES)}")
    return [Cell(*values) for values in
            itertools.product(manoeuvres, MUS, SPEEDS_KMH, MASS_OFFSETS_KG, LAG_FACTORS)]


# ---------------------------------------------------------------------------- one run

def run_duration_s(cell: Cell) -> float:
    """Run length (s): to the end of the course plus ``SETTLE_M`` at the target speed, plus
    ``MARGIN_S``; a whole number of control periods."""
    manoeuvre = MANOEUVRES[cell.manoeuvre]
    seconds = (manoeuvre.course_end_x_m + SETTLE_M) / (cell.speed_kmh * _KMH) + MARGIN_S
    period = CONTROL_PERIOD_MS / 1000.0
    return round(math.ceil(seconds / period) * period, 3)


@functools.lru_cache(maxsize=None)
def _path_end_x_m(path_file: Path) -> float:
    return float(read_path_csv(path_file)[-1, 0])


def cell_scenario(cell: Cell) -> Scenario:
    """The cell as a ``Scenario``: its path, mu and mass offset, a constant target speed
    and a start on the path at X = 0 at that speed.

    Raises:
        StudyError: a path that ends before the run's last position plus the horizons.
    """
    manoeuvre = MANOEUVRES[cell.manoeuvre]
    speed = cell.speed_kmh * _KMH
    duration = run_duration_s(cell)
    needed = speed * duration + HORIZON_ROOM_M
    if _path_end_x_m(manoeuvre.path_file) < needed:
        raise StudyError(f"{cell.name}: {manoeuvre.path_file.name} ends at X = "
                         f"{_path_end_x_m(manoeuvre.path_file):.0f} m; the run needs {needed:.0f} m")
    return Scenario(
        name=cell.name,
        description=f"{manoeuvre.title}, {cell.speed_kmh:g} km/h, mu = {cell.mu:g}, "
                    f"{cell.mass_offset_kg:+g} kg, steering lag x{cell.lag_factor:g}",
        source=manoeuvre.path_file,
        duration_s=duration,
        path_id=manoeuvre.path_id,
        path_file=manoeuvre.path_file,
        mu=cell.mu,
        mass_kg=None,
        mass_offset_kg=cell.mass_offset_kg,
        start=StartState(x_m=0.0, y_m=0.0, yaw_rad=0.0, speed_mps=speed),
        speed_profile=SpeedProfile((0.0,), (speed,)),
    )


def plant_params(cell: Cell) -> Any:
    """The plant's ``VehicleParams`` for the cell: the scenario's mu and mass, the steering
    time constant times ``lag_factor`` (rate limit unchanged)."""
    params = cell_scenario(cell).vehicle_params()
    return dataclasses.replace(params,
                               steer_time_constant=params.steer_time_constant * cell.lag_factor)


def build_plant(cell: Cell) -> tuple[Any, Any]:
    """``(FourWheelVehicle, VehicleCommand)`` with :func:`plant_params`."""
    from models.vehicle import FourWheelVehicle, VehicleCommand

    return FourWheelVehicle(plant_params(cell)), VehicleCommand


@dataclass(frozen=True)
class RunRecord:
    """The outcome of one (cell, controller) run.

    ``e_y_rmse`` / ``e_y_max`` (m) and ``heading_rmse`` (rad) are those of the trace as far
    as it went (NaN when the run never started); ``completed`` is False for a run that left
    the road or was stopped, with the reason in ``error``. ``seconds`` is the run's wall time
    in its worker (build included), ``steps`` its control steps.
    """

    controller: str
    manoeuvre: str
    mu: float
    speed_kmh: float
    mass_offset_kg: float
    lag_factor: float
    completed: bool
    e_y_rmse: float
    e_y_max: float
    heading_rmse: float
    error: str
    seconds: float = 0.0
    steps: int = 0
    key: str = ""

    @property
    def cell(self) -> Cell:
        return Cell(self.manoeuvre, self.mu, self.speed_kmh, self.mass_offset_kg, self.lag_factor)

    @property
    def not_run(self) -> bool:
        """True when the controller or the plant could not even be built (no trace)."""
        return not self.completed and self.steps == 0

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "RunRecord":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})

    def csv_row(self) -> dict[str, str]:
        """The :data:`CSV_FIELDS` as text (metrics with 6 decimals, empty when NaN)."""
        row = {name: getattr(self, name) for name in CSV_FIELDS}
        for name in ("e_y_rmse", "e_y_max", "heading_rmse"):
            row[name] = "" if not math.isfinite(row[name]) else f"{row[name]:.6f}"
        row["completed"] = "1" if self.completed else "0"
        for name in ("mu", "speed_kmh", "mass_offset_kg", "lag_factor"):
            row[name] = f"{row[name]:g}"
        return row


def default_factory(name: str) -> Any:
    """``controller.registry.create_controller(name)`` with the default tuning file."""
    from controller.registry import create_controller

    return create_controller(name)


@dataclass(frozen=True)
class SnapshotFactory:
    """``create_controller(name, tuning_path)`` with a copy of the tuning file taken when
    the grid started, so that a tuning sweep writing ``controller/tuning.toml`` meanwhile
    cannot change the runs (their cache key names the copy's digest). Picklable."""

    tuning_path: Path

    def __call__(self, name: str) -> Any:
        from controller.registry import create_controller

        return create_controller(name, self.tuning_path)


def tuning_snapshot(cache_dir: Path) -> Path:
    """Copy ``controller/tuning.toml`` to ``cache_dir/tuning/<sha256[:16]>.toml`` (once per
    content) and return the copy."""
    data = (ROOT / "controller" / "tuning.toml").read_bytes()
    copy = cache_dir / "tuning" / f"{hashlib.sha256(data).hexdigest()[:16]}.toml"
    if not copy.is_file():
        copy.parent.mkdir(parents=True, exist_ok=True)
        partial = copy.with_suffix(f".{os.getpid()}.tmp")
        partial.write_bytes(data)
        os.replace(partial, copy)
    return copy


def run_one(cell: Cell, controller_name: str, factory: ControllerFactory | None = None,
            key: str = "") -> RunRecord:
    """Run one controller on one cell; never raises for a failure of the run itself.

    Args:
        cell: the conditions.
        controller_name: a ``controller.registry`` name (or one ``factory`` knows).
        factory: builds the controller (default :func:`default_factory`).
        key: the cache key, copied into the record.
    """
    factory = factory or default_factory
    started = time.perf_counter()
    nan = float("nan")
    base = dict(controller=controller_name, **cell.as_dict(), key=key)
    try:
        scenario = cell_scenario(cell)
        plant, command_type = build_plant(cell)
        controller = factory(controller_name)
        result = run_closed_loop(scenario, controller, plant=plant, command_type=command_type,
                                 abort_lateral_error_m=LEAVE_ROAD_M)
    except Exception as e:  # noqa: BLE001 - recorded per run; the grid goes on
        return RunRecord(**base, completed=False, e_y_rmse=nan, e_y_max=nan, heading_rmse=nan,
                         error=f"{type(e).__name__}: {e}",
                         seconds=time.perf_counter() - started, steps=0)
    lateral, heading = result.tracking.lateral, result.tracking.heading
    completed = result.completed and lateral.max_abs <= LEAVE_ROAD_M
    if completed:
        error = ""
    elif result.failure:
        error = f"stopped: {result.failure}"
    else:
        error = f"left the road: max |e_Y| = {lateral.max_abs:.2f} m > {LEAVE_ROAD_M} m"
    return RunRecord(**base, completed=completed, e_y_rmse=lateral.rmse, e_y_max=lateral.max_abs,
                     heading_rmse=heading.rmse, error=error,
                     seconds=time.perf_counter() - started, steps=len(result.trace))


# ---------------------------------------------------------------------------- cache

def _artefact_files() -> list[Path]:
    return sorted(p for p in (ROOT / "models" / "artifacts").glob("*")
                  if p.suffix in (".npz", ".json"))


@functools.lru_cache(maxsize=None)
def input_digests(controller_name: str) -> tuple[tuple[str, str], ...]:
    """``(path, sha256)`` of what a run of ``controller_name`` reads: the tuning file, the
    vehicle file, the model artefacts, the path files, and the sources of the controller's
    module and of the runner with every project module they import
    (``studies.provenance.input_digests``)."""
    from studies.provenance import input_digests as digests

    inputs = [ROOT / "controller" / "tuning.toml", ROOT / "models" / "vehicle.toml",
              *_artefact_files(), *(m.path_file for m in MANOEUVRES.values())]
    module = CONTROLLERS[controller_name][0] if controller_name in CONTROLLERS else None
    modules = ["studies.closed_loop", "models.vehicle", *([module] if module else [])]
    return tuple(sorted(digests([str(p) for p in inputs], modules, ROOT).items()))


def run_key(cell: Cell, controller_name: str) -> str:
    """sha256 (hex) over the cell, the controller, the run's settings, the plant's
    parameters and :func:`input_digests`: equal keys mean the run would compute the same."""
    from models.vehicle_params import params_as_dict

    payload = {
        "version": CACHE_VERSION,
        "cell": cell.as_dict(),
        "controller": controller_name,
        "duration_s": run_duration_s(cell),
        "leave_road_m": LEAVE_ROAD_M,
        "plant": params_as_dict(plant_params(cell)),
        "inputs": input_digests(controller_name),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def cache_file(cache_dir: Path, key: str) -> Path:
    return cache_dir / "runs" / f"{key[:24]}.json"


def load_cached(cache_dir: Path, key: str) -> RunRecord | None:
    """The cached record of ``key``, or None (absent, unreadable or of another key)."""
    file = cache_file(cache_dir, key)
    try:
        values = json.loads(file.read_text())
        record = RunRecord.from_dict(values)
    except (OSError, ValueError, TypeError):
        return None
    return record if record.key == key else None


def store(cache_dir: Path, record: RunRecord) -> None:
    """Write ``record`` to the cache (atomically: a killed grid leaves no half file)."""
    file = cache_file(cache_dir, record.key)
    file.parent.mkdir(parents=True, exist_ok=True)
    partial = file.with_suffix(f".{os.getpid()}.tmp")
    partial.write_text(json.dumps(record.as_dict(), indent=1, allow_nan=True) + "\n")
    os.replace(partial, file)


# ---------------------------------------------------------------------------- the grid

@dataclass(frozen=True)
class RunTask:
    """A run for a worker (picklable): the cell, the controller, the key, the factory."""

    cell: Cell
    controller: str
    key: str
    factory: ControllerFactory | None = None


def _run_task(task: RunTask) -> RunRecord:
    return run_one(task.cell, task.controller, task.factory, task.key)


def _task_order(task: RunTask) -> tuple[float, str]:
    """Longest first (NMPC, then long runs), so two workers finish together."""
    return (-run_duration_s(task.cell) * (8.0 if task.controller == "nmpc" else 1.0), task.cell.name)


def run_grid(cells: Sequence[Cell], controllers: Sequence[str], *, cache_dir: Path = DEFAULT_CACHE,
             workers: int = 2, address: str | None = None, use_cache: bool = True,
             show_progress: bool = True, factory: ControllerFactory | None = None) -> list[RunRecord]:
    """Every controller on every cell, from the cache where it holds the run.

    Args:
        cells: the cells (:func:`grid_cells`).
        controllers: registry names.
        cache_dir: the cache folder (one JSON per run under ``runs/``).
        workers: Ray workers (a local Ray with this many CPUs); 1 without ``address`` runs
            in this process.
        address: a Ray cluster to run on (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``).
        use_cache: False recomputes every run (and overwrites its cache entry).
        show_progress: a tqdm bar over the runs to compute (failed count, time left).
        factory: builds the controllers (tests); default the registry with a copy of the
            tuning file taken now (:class:`SnapshotFactory`).

    Returns:
        One record per (cell, controller), cell-major in the order given.

    Raises:
        StudyError: the tuning file changed between the keys and its copy, or another
            input changed while the runs ran (those runs are then dropped from the cache).
    """
    # The inputs as they are now: the keys name them, the runs read them (the tuning from a
    # copy taken here), and they are checked again at the end.
    input_digests.cache_clear()
    if factory is None:
        snapshot = tuning_snapshot(cache_dir)
        factory = SnapshotFactory(snapshot)
        tuning_digest = hashlib.sha256(snapshot.read_bytes()).hexdigest()
        for name in controllers:
            if dict(input_digests(name))["controller/tuning.toml"] != tuning_digest:
                raise StudyError("controller/tuning.toml changed while the grid started; run it again")
    started_digests = {name: input_digests(name) for name in controllers}
    records: dict[tuple[Cell, str], RunRecord] = {}
    pending: list[RunTask] = []
    for cell in cells:
        for name in controllers:
            key = run_key(cell, name)
            cached = load_cached(cache_dir, key) if use_cache else None
            if cached is not None:
                records[(cell, name)] = cached
            else:
                pending.append(RunTask(cell, name, key, factory))
    pending.sort(key=_task_order)
    if show_progress:
        print(f"{len(records)} of {len(records) + len(pending)} runs from the cache "
              f"({cache_dir}); {len(pending)} to run on {max(1, min(workers, len(pending)))} "
              f"worker(s)", file=sys.stderr)
    failed = sum(not r.completed for r in records.values())
    bar = tqdm(total=len(pending), desc="robustness", unit="run", disable=not show_progress,
               dynamic_ncols=True)
    bar.set_postfix(failed=failed)
    with bar:
        for record, keep in _execute(pending, workers, address):
            if keep:
                store(cache_dir, record)
            records[(record.cell, record.controller)] = record
            failed += not record.completed
            bar.set_postfix(failed=failed, last=f"{record.controller} {record.cell.name}",
                            refresh=False)
            bar.update(1)
    input_digests.cache_clear()
    changed = sorted({path for name in controllers
                      for path, digest in set(input_digests(name)) ^ set(started_digests[name])
                      if path != "controller/tuning.toml"})
    if changed:
        # Runs after the change read other inputs than their keys say: drop this call's runs.
        for task in pending:
            cache_file(cache_dir, task.key).unlink(missing_ok=True)
        raise StudyError(f"inputs changed while the grid ran ({', '.join(changed)}); its "
                         f"{len(pending)} new runs were dropped from the cache: run it again")
    return [records[(cell, name)] for cell in cells for name in controllers]


def _execute(tasks: Sequence[RunTask], workers: int, address: str | None) -> Iterator[tuple[RunRecord, bool]]:
    """(record, cache it?) of ``tasks`` as they finish: in this process (one worker, no
    address), else as Ray tasks (``studies.campaign.executors``: a local Ray with
    ``workers`` CPUs, or the cluster at ``address``). A task whose worker died becomes a
    not-run record that is not cached, so the next call retries it."""
    from studies.campaign.executors import open_executor

    if not tasks:
        return
    executor = open_executor(_run_task, address=address, workers=workers,
                             serial=workers <= 1 and address is None)
    try:
        for task, record, worker_error in executor.run(tasks):
            if worker_error is None:
                yield record, True
            else:
                nan = float("nan")
                yield RunRecord(task.controller, **task.cell.as_dict(), completed=False, e_y_rmse=nan,
                                e_y_max=nan, heading_rmse=nan, error=f"worker died: {worker_error}",
                                key=task.key), False
    finally:
        executor.close()


# ---------------------------------------------------------------------------- summary

@dataclass(frozen=True)
class ControllerSummary:
    """One row of the report's table (a)."""

    controller: str
    runs: int
    completed: int
    completed_by_manoeuvre: dict[str, int]
    not_run: int
    common_rmse_mean: float
    common_rmse_median: float
    lowest_count: int


@dataclass(frozen=True)
class GridSummary:
    """What the report shows, measured from the records."""

    controllers: tuple[str, ...]
    cells: tuple[Cell, ...]
    common_cells: tuple[Cell, ...]
    rows: tuple[ControllerSummary, ...]
    #: (mu, speed_kmh) -> (number of common cells, {controller: mean e_Y RMSE}).
    pivot: dict[tuple[float, float], tuple[int, dict[str, float]]]
    #: (mu, speed_kmh) -> {controller: completed runs}, and the runs per group.
    completed_pivot: dict[tuple[float, float], dict[str, int]]
    runs_per_group: int


def by_cell(records: Sequence[RunRecord]) -> dict[Cell, dict[str, RunRecord]]:
    """Records grouped by cell, then controller."""
    grouped: dict[Cell, dict[str, RunRecord]] = {}
    for record in records:
        grouped.setdefault(record.cell, {})[record.controller] = record
    return grouped


def common_completed_cells(records: Sequence[RunRecord], controllers: Sequence[str]) -> list[Cell]:
    """Cells that every one of ``controllers`` completed, in the records' order."""
    return [cell for cell, runs in by_cell(records).items()
            if all(name in runs and runs[name].completed for name in controllers)]


def summarise(records: Sequence[RunRecord], controllers: Sequence[str]) -> GridSummary:
    """Table (a), the pivots, over ``records`` of ``controllers``."""
    grouped = by_cell(records)
    common = common_completed_cells(records, controllers)
    lowest = {name: 0 for name in controllers}
    for cell in common:
        rmse = {name: grouped[cell][name].e_y_rmse for name in controllers}
        best = min(rmse.values())
        for name, value in rmse.items():
            lowest[name] += value == best
    rows = []
    for name in controllers:
        mine = [r for r in records if r.controller == name]
        values = [grouped[cell][name].e_y_rmse for cell in common]
        rows.append(ControllerSummary(
            controller=name, runs=len(mine), completed=sum(r.completed for r in mine),
            completed_by_manoeuvre={m: sum(r.completed for r in mine if r.manoeuvre == m)
                                    for m in MANOEUVRES},
            not_run=sum(r.not_run for r in mine),
            common_rmse_mean=float(np.mean(values)) if values else float("nan"),
            common_rmse_median=float(np.median(values)) if values else float("nan"),
            lowest_count=lowest[name]))
    groups = sorted({(cell.mu, cell.speed_kmh) for cell in grouped})
    pivot = {}
    completed_pivot = {}
    for group in groups:
        in_group = [cell for cell in common if (cell.mu, cell.speed_kmh) == group]
        pivot[group] = (len(in_group), {
            name: float(np.mean([grouped[cell][name].e_y_rmse for cell in in_group]))
            if in_group else float("nan") for name in controllers})
        completed_pivot[group] = {name: sum(
            runs[name].completed for cell, runs in grouped.items()
            if (cell.mu, cell.speed_kmh) == group and name in runs) for name in controllers}
    per_group = len(grouped) // max(1, len(groups))
    return GridSummary(tuple(controllers), tuple(grouped), tuple(common), tuple(rows), pivot,
                       completed_pivot, per_group)


def ranking_line(summary: GridSummary) -> str:
    """The measured ranking by mean e_Y RMSE over the common cells (lower first)."""
    from studies.report import display_name

    if not summary.common_cells:
        return "No cell was completed by every controller: no ranking."
    ordered = sorted(summary.rows, key=lambda row: row.common_rmse_mean)
    chain = " < ".join(f"{display_name(r.controller)} {r.common_rmse_mean:.4f} m" for r in ordered)
    most = max(row.lowest_count for row in summary.rows)
    leaders = [display_name(row.controller) for row in summary.rows if row.lowest_count == most]
    return (f"Measured ranking by mean e_Y RMSE over the {len(summary.common_cells)} cells every "
            f"controller completed (lower is better): {chain}. Lowest e_Y RMSE on the most of "
            f"those cells: {', '.join(leaders)} ({most} of {len(summary.common_cells)}"
            f"{' each' if len(leaders) > 1 else ''}).")


def goal_line(records: Sequence[RunRecord]) -> str | None:
    """Issue 14's goal on the grid, measured: on how many cells that at least one
    controller completed ESO-DKMPC completed with an e_Y RMSE at most LMPC's and NMPC's (a
    run that did not complete counts as an infinite RMSE). None without those three."""
    grouped = by_cell(records)
    names = ("eso-dkmpc", "lmpc", "nmpc")
    cells = [cell for cell, runs in grouped.items()
             if all(n in runs for n in names) and any(r.completed for r in runs.values())]
    if not cells:
        return None

    def rmse(run: RunRecord) -> float:
        return run.e_y_rmse if run.completed else math.inf

    met = sum(grouped[c]["eso-dkmpc"].completed
              and rmse(grouped[c]["eso-dkmpc"]) <= min(rmse(grouped[c]["lmpc"]), rmse(grouped[c]["nmpc"]))
              for c in cells)
    return (f"Issue 14's goal on the grid: ESO-DKMPC's e_Y RMSE at most LMPC's and NMPC's on "
            f"{met} of the {len(cells)} cells that at least one controller completed "
            f"({'met' if met * 2 > len(cells) else 'not met'}: \"most\" needs more than "
            f"{len(cells) // 2}; a run that did not complete counts as an infinite RMSE).")


def observer_line(records: Sequence[RunRecord]) -> str | None:
    """What the observer adds on the grid (issue 35): ESO-DKMPC against DKMPC, the same
    controller without it, head to head on the cells either completed, and on those with a
    model mismatch (mass +300 kg or steering lag x3); a run that did not complete counts as
    an infinite RMSE, a tie as neither winning. None without both controllers."""
    grouped = by_cell(records)
    pairs = [(runs["eso-dkmpc"], runs["dkmpc"]) for runs in grouped.values()
             if "eso-dkmpc" in runs and "dkmpc" in runs and (runs["eso-dkmpc"].completed or runs["dkmpc"].completed)]
    if not pairs:
        return None

    def rmse(run: RunRecord) -> float:
        return run.e_y_rmse if run.completed else math.inf

    def count(selected: list[tuple[RunRecord, RunRecord]]) -> str:
        wins = sum(rmse(eso) < rmse(dk) for eso, dk in selected)
        losses = sum(rmse(eso) > rmse(dk) for eso, dk in selected)
        return f"{wins} of {len(selected)} (DKMPC lower on {losses})"

    mismatch = [(eso, dk) for eso, dk in pairs if eso.mass_offset_kg > 0.0 or eso.lag_factor > 1.0]
    return (f"The observer, head to head: ESO-DKMPC's e_Y RMSE below DKMPC's on {count(pairs)} of the "
            f"cells either completed; on the model-mismatch cells (mass +300 kg or steering lag x3) on "
            f"{count(mismatch)}.")


# ---------------------------------------------------------------------------- outputs

def write_csv(records: Sequence[RunRecord], file: Path) -> None:
    """``robustness.csv``: :data:`CSV_FIELDS`, one row per run."""
    with file.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_FIELDS, lineterminator="\n")
        writer.writeheader()
        for record in records:
            writer.writerow(record.csv_row())


def _number(value: float, decimals: int = 4) -> str:
    return "-" if not math.isfinite(value) else f"{value:.{decimals}f}"


def inputs_note(root: Path = ROOT) -> str:
    """Which commits the tuning file and the default model artefact come from (the last
    commit that changed each, and ``git log -1 -- models/artifacts/dk_d5.npz
    controller/tuning.toml`` for both), and whether the working tree changes them."""
    files = {"controller/tuning.toml": "tuning", "models/artifacts/dk_d5.npz": "artefact"}

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                              check=True, timeout=30).stdout

    try:
        last = {name: git("log", "-1", "--format=%h %s", "--", name).strip() for name in files}
        both = git("log", "-1", "--format=%h", "--", *files).strip()
        dirty = git("status", "--porcelain", "--", *files)
    except (OSError, subprocess.SubprocessError):
        return "tuning and artefact commits: unknown (no git)"
    parts = []
    for name, line in last.items():
        sha, _, subject = line.partition(" ")
        subject = subject if len(subject) <= 70 else subject[:67] + "..."
        parts.append(f"`{name}` of commit `{sha or '?'}` (\"{subject}\")")
    note = "; ".join(parts) + f" (last commit of either: `{both or '?'}`)"
    changed = [line[3:] for line in dirty.splitlines() if line.strip()]  # "XY path"
    if changed:
        note += ("; uncommitted changes to them in the working tree were used: "
                 + ", ".join(f"`{name}`" for name in changed))
    return note


def report_markdown(records: Sequence[RunRecord], summary: GridSummary, *, command: str,
                    workers: int, inputs: str) -> str:
    """``robustness.md``."""
    from studies.report import display_name

    names = summary.controllers
    cells = summary.cells
    axes = {"manoeuvre": sorted({c.manoeuvre for c in cells}), "mu": sorted({c.mu for c in cells}),
            "speed (km/h)": sorted({c.speed_kmh for c in cells}),
            "mass offset (kg)": sorted({c.mass_offset_kg for c in cells}),
            "steering lag factor": sorted({c.lag_factor for c in cells})}
    run_seconds = sum(r.seconds for r in records)
    lines = [
        "# Robustness grid on our plant (`make robustness`)",
        "",
        f"`{command}`: every controller in closed loop with the four-wheel plant "
        "(`studies.closed_loop`, no CAN) on every cell of the grid; see docs/robustness.md.",
        "",
        "- Grid: " + "; ".join(f"{axis} {' / '.join(f'{v:g}' if isinstance(v, float) else v for v in values)}"
                                 for axis, values in axes.items())
        + f": {len(cells)} cells per controller, {len(records)} runs.",
        f"- A run starts on the path at X = 0 at the target speed (held constant) and lasts "
        f"(end of the course + {SETTLE_M:g} m) / speed + {MARGIN_S:g} s; it is completed when "
        f"the runner does not stop it and max |e_Y| <= {LEAVE_ROAD_M:g} m (the road).",
        f"- Inputs: {inputs}.",
        f"- Machine: {machine_description()}; {workers} worker process(es); the runs took "
        f"{run_seconds / 60:.1f} min of worker time in all (cached runs count their own run).",
        "",
        f"## (a) Per controller, over the {len(summary.common_cells)} cells every controller completed",
        "",
        "| controller | completed | " + " | ".join(f"{m} completed" for m in MANOEUVRES)
        + " | not run | mean e_Y RMSE (m) | median e_Y RMSE (m) | lowest e_Y RMSE (cells) |",
        "|---|---|" + "---|" * len(MANOEUVRES) + "---|---|---|---|",
    ]
    for row in summary.rows:
        per_manoeuvre = " | ".join(
            f"{row.completed_by_manoeuvre[m]} of {sum(1 for c in cells if c.manoeuvre == m)}"
            for m in MANOEUVRES)
        lines.append(f"| {display_name(row.controller)} | {row.completed} of {row.runs} | "
                     f"{per_manoeuvre} | {row.not_run} | {_number(row.common_rmse_mean)} | "
                     f"{_number(row.common_rmse_median)} | {row.lowest_count} of "
                     f"{len(summary.common_cells)} |")
    lines += [
        "",
        "Not run: the controller or the plant could not be built (`error` in robustness.csv). "
        "Lowest: the cells where the controller's e_Y RMSE is the smallest of all (ties count "
        "for each).",
        "",
        "## (b) e_Y RMSE (m) by mu x speed, over the cells every controller completed",
        "",
        "Mean over the other axes (manoeuvre, mass, steering lag) of the cells in the group "
        "that every controller completed; `cells` is how many.",
        "",
        "| mu | speed (km/h) | cells | " + " | ".join(display_name(n) for n in names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for (mu, speed), (count, values) in summary.pivot.items():
        best = min((v for v in values.values() if math.isfinite(v)), default=math.nan)
        shown = [(f"**{_number(values[n])}**" if values[n] == best else _number(values[n]))
                 for n in names]
        lines.append(f"| {mu:g} | {speed:g} | {count} | " + " | ".join(shown) + " |")
    lines += ["", "Bold: the lowest of the row.", "", "## (c) Ranking", "", ranking_line(summary)]
    goal = goal_line(records)
    if goal:
        lines += ["", goal]
    observer = observer_line(records)
    if observer:
        lines += ["", observer]
    lines += [
        "",
        f"## (d) Completed runs by mu x speed (of {summary.runs_per_group} per controller)",
        "",
        "| mu | speed (km/h) | " + " | ".join(display_name(n) for n in names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for (mu, speed), counts in summary.completed_pivot.items():
        lines.append(f"| {mu:g} | {speed:g} | " + " | ".join(str(counts[n]) for n in names) + " |")
    errors = [r for r in records if r.not_run]
    if errors:
        lines += ["", f"## Runs that could not be built ({len(errors)})", ""]
        lines += [f"- {display_name(r.controller)} on {r.cell.name}: {r.error}" for r in errors[:10]]
        if len(errors) > 10:
            lines.append(f"- ... and {len(errors) - 10} more (robustness.csv)")
    lines += ["", "Per run: robustness.csv. Figure: robustness.png.", ""]
    return "\n".join(lines)


def plot_heatmaps(records: Sequence[RunRecord], controllers: Sequence[str], file: Path,
                  mass_offset_kg: float = 0.0, lag_factor: float = 1.0) -> None:
    """``robustness.png``: one heat map of e_Y RMSE over mu (rows) x speed (columns) per
    controller (columns of panels) and manoeuvre (rows of panels), at ``mass_offset_kg``
    and ``lag_factor``; one logarithmic colour scale; a run not completed is a grey cell
    marked "off"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from studies.report import display_name

    chosen = [r for r in records
              if r.mass_offset_kg == mass_offset_kg and r.lag_factor == lag_factor]
    manoeuvres = [m for m in MANOEUVRES if any(r.manoeuvre == m for r in chosen)]
    mus = sorted({r.mu for r in chosen})
    speeds = sorted({r.speed_kmh for r in chosen})
    done = [r.e_y_rmse for r in chosen if r.completed and r.e_y_rmse > 0.0]
    low, high = (min(done), max(done)) if done else (1e-3, LEAVE_ROAD_M)
    norm = LogNorm(vmin=low, vmax=max(high, low * 1.01))
    figure, axes = plt.subplots(max(1, len(manoeuvres)), max(1, len(controllers)),
                                figsize=(2.6 * len(controllers) + 1.2, 2.6 * len(manoeuvres) + 1.0),
                                squeeze=False, constrained_layout=True)
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    image = None
    lookup = {(r.manoeuvre, r.controller, r.mu, r.speed_kmh): r for r in chosen}
    for i, manoeuvre in enumerate(manoeuvres):
        for j, name in enumerate(controllers):
            ax = axes[i][j]
            grid = np.full((len(mus), len(speeds)), np.nan)
            for a, mu in enumerate(mus):
                for b, speed in enumerate(speeds):
                    run = lookup.get((manoeuvre, name, mu, speed))
                    if run is not None and run.completed:
                        grid[a, b] = run.e_y_rmse
                    text = ("-" if run is None else f"{run.e_y_rmse:.3f}" if run.completed else "off")
                    ax.text(b, a, text, ha="center", va="center", fontsize=8,
                            color="black" if run is None or not run.completed
                            or norm(run.e_y_rmse) > 0.6 else "white")
            image = ax.imshow(np.ma.masked_invalid(grid), origin="lower", cmap=cmap, norm=norm,
                              aspect="auto")
            ax.set_xticks(range(len(speeds)), [f"{s:g}" for s in speeds])
            ax.set_yticks(range(len(mus)), [f"{m:g}" for m in mus])
            if i == len(manoeuvres) - 1:
                ax.set_xlabel("speed (km/h)")
            if j == 0:
                ax.set_ylabel(f"{manoeuvre}\nmu")
            if i == 0:
                ax.set_title(display_name(name))
    if image is not None:
        figure.colorbar(image, ax=axes, shrink=0.8, label="e_Y RMSE (m), log scale")
    figure.suptitle(f"e_Y RMSE (m) over mu x speed, mass {mass_offset_kg:+g} kg, steering lag "
                    f"x{lag_factor:g}\ngrey 'off': not completed (|e_Y| > {LEAVE_ROAD_M:g} m or "
                    "stopped)")
    figure.savefig(file, dpi=110)
    plt.close(figure)


def write_outputs(records: Sequence[RunRecord], controllers: Sequence[str], out: Path, *,
                  command: str, workers: int) -> GridSummary:
    """Write ``robustness.md``, ``.csv`` and ``.png`` into ``out``; return the summary."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(records, controllers)
    write_csv(records, out / "robustness.csv")
    (out / "robustness.md").write_text(report_markdown(
        records, summary, command=command, workers=workers, inputs=inputs_note()))
    plot_heatmaps(records, controllers, out / "robustness.png")
    return summary


# ---------------------------------------------------------------------------- CLI

def main(argv: list[str] | None = None) -> int:
    """CLI entry point (see the module docstring); returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.robustness_grid", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--controllers", nargs="+", choices=ALL_CONTROLLER_NAMES, default=None,
                        help=f"controllers (default: {' '.join(GRID_CONTROLLERS)}; "
                             f"--quick: {' '.join(QUICK_CONTROLLERS)})")
    parser.add_argument("--manoeuvres", nargs="+", choices=tuple(MANOEUVRES), default=tuple(MANOEUVRES),
                        help="manoeuvres (default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help="the smoke subset: 2 controllers x 2 cells, into build/robustness-smoke/")
    parser.add_argument("--workers", type=int, default=2,
                        help="Ray workers (default: 2; 1 runs in this process); on a cluster the "
                             "most runs at once")
    parser.add_argument("--address", default=None,
                        help="Ray cluster to use: auto, HOST:PORT or ray://HOST:PORT "
                             "(default: a local Ray on 127.0.0.1)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: results/)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                        help="cache folder (default: build/robustness/)")
    parser.add_argument("--no-cache", action="store_true", help="recompute every run")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--debug", action="store_true", help="tracebacks on errors")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    controllers = tuple(args.controllers or (QUICK_CONTROLLERS if args.quick else GRID_CONTROLLERS))
    out = args.out or (QUICK_OUT if args.quick else ROOT / "results")
    command = "make robustness-smoke" if args.quick else "make robustness"
    started = time.monotonic()
    try:
        cells = list(QUICK_CELLS) if args.quick else grid_cells(args.manoeuvres)
        records = run_grid(cells, controllers, cache_dir=args.cache, workers=args.workers,
                           address=args.address, use_cache=not args.no_cache, show_progress=not args.no_progress)
        summary = write_outputs(records, controllers, out, command=command, workers=args.workers)
    except (HilError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 1
    from studies.report import display_name

    for row in summary.rows:
        print(f"{display_name(row.controller):<10} completed {row.completed:3d} of {row.runs}  "
              f"mean / median e_Y RMSE over common cells {_number(row.common_rmse_mean)} / "
              f"{_number(row.common_rmse_median)} m  lowest on {row.lowest_count}")
    print(ranking_line(summary))
    goal = goal_line(records)
    if goal:
        print(goal)
    observer = observer_line(records)
    if observer:
        print(observer)
    print(f"wrote {out}/robustness.md, robustness.csv, robustness.png "
          f"({len(records)} runs, {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    # Run the imported module's main, not this __main__ copy: the workers return records of
    # studies.robustness_grid's classes, which must be the ones the grid compares with.
    from studies.robustness_grid import main as _main

    sys.exit(_main())

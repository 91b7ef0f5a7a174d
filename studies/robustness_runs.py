"""The robustness grid's runs and their cache (``make robustness``, run by
``studies.robustness_grid``): one controller on one cell in closed loop (:func:`run_one`, a
:class:`RunRecord`), the cache keyed by everything a run reads (:func:`run_key`), and every
run of the grid, from the cache or on the campaigns' executors (:func:`run_grid`).
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from controller.registry import CONTROLLERS
from hil.errors import StudyError
from studies.closed_loop import run_closed_loop
from studies.robustness_cells import (MANOEUVRES, Cell, build_plant, cell_scenario, plant_params,
                                      run_duration_s)

ROOT = Path(__file__).resolve().parent.parent

#: A run that gets farther than this from the path (m) has left the road: not completed.
LEAVE_ROAD_M = 2.0
#: Bump when what a run computes changes in a way the key's other parts do not show.
CACHE_VERSION = 1
#: Default folder of the cache.
DEFAULT_CACHE = ROOT / "build" / "robustness"

#: One row of ``robustness.csv`` per run, in this order.
CSV_FIELDS = ("controller", "manoeuvre", "mu", "speed_kmh", "mass_offset_kg", "lag_factor",
              "completed", "e_y_rmse", "e_y_max", "heading_rmse", "error")

#: Builds a controller from its registry name (``controller.registry.create_controller``
#: by default); a module-level function, so that it reaches spawned workers.
ControllerFactory = Callable[[str], Any]


# ---------------------------------------------------------------------------- one run

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

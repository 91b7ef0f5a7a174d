"""The campaign runner: cells to workers (Ray, or this process), results cached per cell,
rows written as they complete.

Cache: ``DIR/cache/<key>.json`` per finished cell. The key (:func:`cell_key`) hashes the
cell's values, its scenario file as the worker gets it, the digest of its path file and
model artefact, and the code version (:func:`code_version`: the source files of the cell
runner and of every project module it imports, transitively, plus the tuning, vehicle, DBC
and default model files). A C ECU cell's key also hashes the executable and its data file
(:data:`C_ECU_FILES`: what ``make firmware`` built); a Python cell's key material is what
it was before the ``ecu`` axis existed (no ``ecu`` entry), so its key does not depend on
whether the grid has the axis. A re-run into the same DIR computes only the cells without a
cached result; editing a source file or an artefact recomputes what it could change.
A cell whose run raised is cached with its error (the same inputs fail the same way); a
cell whose worker died (Ray) is recorded in the rows but not cached, so the next run
retries it. A ``fault_case`` cell is never cached (:func:`cell_cacheable`: its verdict holds
wall-clock measurements; ``studies.campaign.fault_case_cell``). A ``prediction`` cell
(Table I: a model row x a seed, ``studies.campaign.prediction_grid``) has its own key
(``studies.campaign.prediction_cell``: the row, the seed, the data set's hash and the code of
that module and its imports) and keeps its trained model in DIR beside ``cache/``.

Exclusive cells (``Cell.exclusive``: the fault cases that measure the ECU's own wall-clock
behaviour) run after every other cell, one at a time in this process, once the executor's
workers are released (:func:`run_campaign`).

The cells run on ``studies.campaign.executors`` (Ray, local or a cluster, or this process),
which the other long studies share. Ctrl-C cancels the cells in flight and keeps every
finished one.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from firmware_sim.native import DEFAULT_DATA
from hil.errors import HilError
from hil.session import C_ECU_EXECUTABLE
from studies.campaign.cell import ROOT, CellJob
from studies.campaign.executors import Executor, SerialExecutor
from studies.campaign.fault_case_cell import FaultCaseJob, fault_case_job, run_fault_case_cell
from studies.campaign.grid import (DEFAULT_ECU, DEFAULT_TUNING, FAULT_CASE_RUNNER, HIL_RUNNER, NO_DISTURBANCE,
                                   PREDICTION_RUNNER, Cell, Grid, effective_values, model_file, to_toml)

if TYPE_CHECKING:
    from studies.campaign.prediction_grid import PredictionGrid

#: Bump when what a cell computes changes in a way the key's other parts do not show.
CACHE_VERSION = 1
#: Data files every cell reads (besides its scenario, path and model).
DATA_FILES = ("controller/tuning.toml", "models/vehicle.toml", "can_defs/vehicle.dbc",
              "models/artifacts/dk_d5.npz", "models/artifacts/dk_d5.json",
              "models/artifacts/dmdc.npz", "models/artifacts/dmdc.json")
#: Modules whose sources (and their imports') make a cell's result.
CELL_MODULES = ("studies.campaign.cell", "hil.session", "firmware_sim.ecu", "controller.registry")
#: What a C ECU cell runs besides the Python side: ``make firmware``'s executable
#: (statically linked, the generated QPs and codecs inside), its data file (tuning, Koopman
#: model, bicycle) and the tool that converts another model artefact to such a file.
C_ECU_FILES = (C_ECU_EXECUTABLE, DEFAULT_DATA, ROOT / "firmware" / "tools" / "ecu_data.py")


class CampaignError(HilError):
    """The campaign cannot run (Ray missing or unreachable, unwritable output)."""


# ---------------------------------------------------------------------------- keys

def _digest(path: Path) -> str:
    from studies.provenance import file_digest

    return file_digest(path)


def code_version(root: Path = ROOT, modules: tuple[str, ...] = CELL_MODULES,
                 data_files: tuple[str, ...] = DATA_FILES) -> str:
    """sha256 over the cell runner's source files (``modules`` and the project modules they
    import, transitively) and ``data_files``: by default a scenario cell's
    (:data:`CELL_MODULES`, :data:`DATA_FILES`)."""
    from studies.provenance import combined_digest, module_sources

    files = {p.relative_to(root).as_posix(): _digest(p) for p in module_sources(modules, root)}
    files.update({name: _digest(root / name) for name in data_files})
    return combined_digest(files)


def grid_code_version(grid: Grid | PredictionGrid) -> str:
    """:func:`code_version` of ``grid``'s cells: a ``prediction`` grid's modules and files
    (``studies.campaign.prediction_cell``), else a scenario cell's."""
    if is_prediction(grid):
        from studies.campaign.prediction_cell import PREDICTION_DATA_FILES, PREDICTION_MODULES

        return code_version(modules=PREDICTION_MODULES, data_files=PREDICTION_DATA_FILES)
    return code_version()


def is_prediction(grid: Grid | PredictionGrid) -> bool:
    """Whether ``grid`` is a ``prediction`` grid (Table I's model rows x seeds). Its modules
    are imported only then: they import the trainer (torch)."""
    return getattr(grid, "runner", None) == PREDICTION_RUNNER


def _repo_relative(path: Path) -> str:
    try:
        return "{ROOT}/" + Path(path).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def check_c_ecu_built(grid: Grid) -> None:
    """Before any cell runs: the C ECU's build exists when the grid has C cells.

    Raises:
        CampaignError: naming the missing file and ``make firmware``.
    """
    c_cells = sum(1 for cell in grid.cells if getattr(cell, "ecu", None) == "c")
    missing = [path for path in C_ECU_FILES if not path.is_file()]
    if c_cells and missing:
        raise CampaignError(f"{grid.source}: axes.ecu has \"c\" ({c_cells} of the cells) but the "
                            f"C ECU's {missing[0]} is missing: run `make firmware` first")


def cell_cacheable(cell: Cell) -> bool:
    """Whether ``cell``'s row goes to the cache: every cell but a ``fault_case`` one, whose
    verdict holds wall-clock measurements (reaction times and CPU share of the lost bus,
    wall times) that a rerun would not repeat, and whose campaign checks the ECU as it is."""
    return cell.runner != FAULT_CASE_RUNNER


def cell_task(grid: Grid | PredictionGrid) -> Callable[[Any], dict[str, Any]]:
    """The executors' task function for ``grid``'s cells: a ``prediction`` or ``fault_case``
    grid's (each runner stands alone on its axis), else the scenario runners' ``run_cell``."""
    if is_prediction(grid):
        from studies.campaign.prediction_cell import run_prediction_cell

        return run_prediction_cell
    if any(cell.runner == FAULT_CASE_RUNNER for cell in grid.cells):
        return run_fault_case_cell
    from studies.campaign.cell import run_cell

    return run_cell


def cell_job(grid: Grid, cell: Cell, version: str) -> CellJob | FaultCaseJob:
    """The worker's job for ``cell``, with its cache key (a C cell: after
    :func:`check_c_ecu_built`; a ``fault_case`` cell: its own job, never cached)."""
    if cell.runner == FAULT_CASE_RUNNER:
        return fault_case_job(grid, cell)
    document = grid.scenario_document(cell)
    path_file = Path(document["path"]["file"])
    document["path"]["file"] = _repo_relative(path_file)
    text = to_toml(document)
    artefact = model_file(grid, cell.model)
    model = None if artefact is None else artefact.relative_to(ROOT).as_posix()
    digests = {"path": _digest(path_file)}
    if artefact is not None:
        digests.update(model=_digest(artefact), model_json=_digest(artefact.with_suffix(".json")))
    values = cell.as_dict()
    if cell.disturbance == NO_DISTURBANCE:
        del values["disturbance"]  # as before the disturbance axis (its scenario text says it)
    del values["case"]  # only a fault_case cell has one
    del values["tuning"]  # the override itself goes into the key (below), not its name
    if cell.runner == HIL_RUNNER:
        del values["runner"]  # the key material of a cell over CAN as before the runner axis
    if cell.ecu == DEFAULT_ECU:
        # the key material of a Python cell as before the ecu axis: its cached results stay
        del values["ecu"]
    else:
        digests.update({path.name: _digest(path) for path in C_ECU_FILES})
    facts = {"version": CACHE_VERSION, "cell": values, "scenario": text, "digests": digests,
             "code": version}
    if grid.keep_trace:
        facts["trace"] = True  # such a row has more in it (a grid without it: the key as before)
    override = tuple(grid.tunings.get(cell.tuning, ())) if cell.tuning != DEFAULT_TUNING else ()
    tuning_text = None if grid.tuning_file is None else grid.tuning_file.read_text(encoding="utf-8")
    # Only a grid with a tuning axis, tuning file or road limit adds these: every other
    # grid's keys stay as they were before them.
    if override or tuning_text is not None:
        facts["tuning"] = {"file": tuning_text, "override": [list(pair) for pair in override]}
    if grid.leave_road_m is not None:
        facts["leave_road_m"] = grid.leave_road_m
    material = json.dumps(facts, sort_keys=True)
    key = hashlib.sha256(material.encode()).hexdigest()[:24]
    return CellJob(key=key, controller=cell.controller, scenario_toml=text, model=model,
                   ecu=cell.ecu, keep_trace=grid.keep_trace, runner=cell.runner,
                   tuning_toml=tuning_text, tuning_override=override, leave_road_m=grid.leave_road_m)


def cell_key(grid: Grid, cell: Cell, version: str | None = None) -> str:
    """The cache key of ``cell`` (see the module docstring)."""
    return cell_job(grid, cell, version or code_version()).key


def campaign_jobs(grid: Grid | PredictionGrid, out_dir: Path, version: str | None = None) -> list[Any]:
    """The workers' jobs of every cell of ``grid`` (in grid order), keyed for the code
    ``version`` (default: this checkout's, :func:`grid_code_version`); a ``prediction``
    grid's trained models go to ``out_dir``.

    Raises:
        CampaignError: a ``prediction`` grid's data set is missing.
    """
    version = version or grid_code_version(grid)
    if not is_prediction(grid):
        return [cell_job(grid, cell, version) for cell in grid.cells]
    from models.koopman_data import dataset_hash
    from studies.campaign.prediction_cell import prediction_job

    if not grid.data_dir.is_dir():
        raise CampaignError(f"{grid.source}: run.data: no data set in {grid.data_dir} (`make train` or "
                            "`python -m models.data generate --out DIR --profile wide` writes one)")
    data_hash = dataset_hash(grid.data_dir)
    return [prediction_job(grid, cell, version, out_dir, data_hash) for cell in grid.cells]


def cell_axes(grid: Grid | PredictionGrid, cell: Any) -> dict[str, Any]:
    """The axis columns of ``cell``'s row (a scenario cell's: :func:`effective_values`)."""
    if is_prediction(grid):
        return cell.as_dict()
    return effective_values(grid.scenario_document(cell), cell)


# ---------------------------------------------------------------------------- cache

class Cache:
    """Finished cells as ``DIR/cache/<key>.json`` (written atomically)."""

    def __init__(self, out_dir: Path) -> None:
        self.folder = out_dir / "cache"
        self.folder.mkdir(parents=True, exist_ok=True)

    def get(self, key: str) -> dict[str, Any] | None:
        path = self.folder / f"{key}.json"
        try:
            return json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def put(self, key: str, row: dict[str, Any]) -> None:
        path = self.folder / f"{key}.json"
        temporary = path.with_suffix(".tmp")
        temporary.write_text(json.dumps(row, indent=1, allow_nan=True) + "\n", encoding="utf-8")
        os.replace(temporary, path)


# ---------------------------------------------------------------------------- the campaign

@dataclass
class CampaignResult:
    """Rows in grid order (finished cells only), counts and the wall time."""

    rows: list[dict[str, Any]]
    computed: int
    cached: int
    failed: int
    total: int
    wall_s: float
    executor: str
    interrupted: bool = False
    notes: list[str] = field(default_factory=list)


def run_campaign(grid: Grid | PredictionGrid, out_dir: Path, executor: Executor, *, progress: bool = True,
                 on_row: Callable[[dict[str, Any]], None] | None = None) -> CampaignResult:
    """Run every cell of ``grid`` not yet cached in ``out_dir``; a KeyboardInterrupt stops
    the campaign and returns what finished (``interrupted`` True). The exclusive cells
    (``Cell.exclusive``) run last, one at a time in this process, after ``executor`` is
    closed (so no worker holds a core meanwhile; closing it again is harmless)."""
    from tqdm import tqdm

    started = time.monotonic()
    check_c_ecu_built(grid)
    cache = Cache(out_dir)
    jobs = campaign_jobs(grid, out_dir)
    axes = {job.key: cell_axes(grid, cell) for cell, job in zip(grid.cells, jobs)}
    results: dict[str, dict[str, Any]] = {}
    for job in jobs:
        cached = cache.get(job.key) if getattr(job, "cacheable", True) else None
        if cached is not None:
            results[job.key] = cached
    todo = [job for job in jobs if job.key not in results]
    cached_count = len(results)
    failed = sum(1 for r in results.values() if not r.get("completed"))
    computed = 0
    interrupted = False
    bar = tqdm(total=len(jobs), initial=cached_count, unit="cell", disable=not progress,
               desc=grid.name, dynamic_ncols=True)
    bar.set_postfix(failed=failed, cached=cached_count)
    stream = _shared_then_exclusive(executor, todo, cell_task(grid))
    try:
        for job, row, worker_error in stream:
            if worker_error is not None:  # recorded, not cached: the next run retries it
                row = {"key": job.key, "completed": 0, "end_reason": "error", "error": worker_error}
            row = {**axes[job.key], **row}
            if worker_error is None and getattr(job, "cacheable", True):
                cache.put(job.key, row)
            results[job.key] = row
            computed += 1
            failed += 0 if row.get("completed") else 1
            if on_row is not None:
                on_row(row)
            bar.update(1)
            bar.set_postfix(failed=failed, cached=cached_count)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        stream.close()  # cancels the cells in flight
        bar.close()
    rows = [{**axes[job.key], **results[job.key]} for job in jobs if job.key in results]
    return CampaignResult(rows=rows, computed=computed, cached=cached_count,
                          failed=sum(1 for r in rows if not r.get("completed")),
                          total=len(jobs), wall_s=time.monotonic() - started,
                          executor=executor.description, interrupted=interrupted)


def _shared_then_exclusive(executor: Executor, jobs: list[Any],
                           task: Callable[[Any], Any]) -> Iterator[tuple[Any, Any, str | None]]:
    """The jobs on ``executor``, then the exclusive ones alone in this process (``task``:
    the grid's cell task, :func:`cell_task`)."""
    alone = [job for job in jobs if getattr(job, "exclusive", False)]
    yield from executor.run([job for job in jobs if not getattr(job, "exclusive", False)])
    if alone:
        executor.close()
        yield from SerialExecutor(task).run(alone)


def cached_rows(grid: Grid | PredictionGrid, out_dir: Path, version: str | None = None) -> list[dict[str, Any]]:
    """The rows of ``grid``'s cells cached in ``out_dir`` for the code ``version`` (default:
    this checkout's), in grid order; cells without a cached result are left out."""
    cache = Cache(out_dir)
    rows = (cache.get(job.key) for job in campaign_jobs(grid, out_dir, version))
    return [row for row in rows if row]


def finished_rows(rows: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of cells that ran (completed or not) without an error."""
    return [r for r in rows if not r.get("error")]

"""The campaign runner: cells to workers (Ray, or this process), results cached per cell,
rows written as they complete.

Cache: ``DIR/cache/<key>.json`` per finished cell. The key (:func:`cell_key`) hashes the
cell's values, its scenario file as the worker gets it, the digest of its path file and
model artefact, and the code version (:func:`code_version`: the source files of the cell
runner and of every project module it imports, transitively, plus the tuning, vehicle, DBC
and default model files). A re-run into the same DIR computes only the cells without a
cached result; editing a source file or an artefact recomputes what it could change.
A cell whose run raised is cached with its error (the same inputs fail the same way); a
cell whose worker died (Ray) is recorded in the rows but not cached, so the next run
retries it.

Ray: by default a local Ray on this machine (one worker per core, bound to 127.0.0.1, no
dashboard, a small object store, usage statistics off); ``address`` (``auto``,
``HOST:PORT``, ``ray://HOST:PORT``) joins an existing cluster instead. Workers get
``OPENBLAS_NUM_THREADS=1``, ``OMP_NUM_THREADS=1``, ``MKL_NUM_THREADS=1`` through the
runtime environment. Ctrl-C cancels the cells in flight and keeps every finished one.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.errors import HilError
from studies.campaign.cell import ROOT, CellJob, run_cell
from studies.campaign.grid import Cell, Grid, effective_values, model_file, to_toml

#: Bump when what a cell computes changes in a way the key's other parts do not show.
CACHE_VERSION = 1
#: Environment of every worker: one BLAS / OpenMP thread (tiny matrices, cores are busy).
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Object store of the local Ray (bytes): the cells pass a few kB each.
LOCAL_OBJECT_STORE_BYTES = 128 * 1024 * 1024
#: Data files every cell reads (besides its scenario, path and model).
DATA_FILES = ("controller/tuning.toml", "models/vehicle.toml", "can_defs/vehicle.dbc",
              "models/artifacts/dk_d5.npz", "models/artifacts/dk_d5.json",
              "models/artifacts/dmdc.npz", "models/artifacts/dmdc.json")
#: Modules whose sources (and their imports') make a cell's result.
CELL_MODULES = ("studies.campaign.cell", "hil.session", "firmware_sim.ecu", "controller.registry")


class CampaignError(HilError):
    """The campaign cannot run (Ray missing or unreachable, unwritable output)."""


# ---------------------------------------------------------------------------- keys

def _digest(path: Path) -> str:
    from studies.provenance import file_digest

    return file_digest(path)


def code_version(root: Path = ROOT) -> str:
    """sha256 over the cell runner's source files (transitively imported project modules)
    and :data:`DATA_FILES`."""
    from studies.provenance import combined_digest, module_sources

    files = {p.relative_to(root).as_posix(): _digest(p) for p in module_sources(CELL_MODULES, root)}
    files.update({name: _digest(root / name) for name in DATA_FILES})
    return combined_digest(files)


def _repo_relative(path: Path) -> str:
    try:
        return "{ROOT}/" + Path(path).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def cell_job(grid: Grid, cell: Cell, version: str) -> CellJob:
    """The worker's job for ``cell``, with its cache key."""
    document = grid.scenario_document(cell)
    path_file = Path(document["path"]["file"])
    document["path"]["file"] = _repo_relative(path_file)
    text = to_toml(document)
    artefact = model_file(grid, cell.model)
    model = None if artefact is None else artefact.relative_to(ROOT).as_posix()
    digests = {"path": _digest(path_file)}
    if artefact is not None:
        digests.update(model=_digest(artefact), model_json=_digest(artefact.with_suffix(".json")))
    material = json.dumps({"version": CACHE_VERSION, "cell": cell.as_dict(), "scenario": text,
                           "digests": digests, "code": version}, sort_keys=True)
    key = hashlib.sha256(material.encode()).hexdigest()[:24]
    return CellJob(key=key, controller=cell.controller, scenario_toml=text, model=model)


def cell_key(grid: Grid, cell: Cell, version: str | None = None) -> str:
    """The cache key of ``cell`` (see the module docstring)."""
    return cell_job(grid, cell, version or code_version()).key


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


# ---------------------------------------------------------------------------- executors

#: A finished job: (job, row, cache it?).
Finished = tuple[CellJob, dict[str, Any], bool]


class SerialExecutor:
    """Runs the cells one by one in this process (``--serial``; tests, debugging)."""

    workers = 1
    description = "this process, one cell at a time"

    def __init__(self, cell_function: Callable[[CellJob], dict[str, Any]] = run_cell) -> None:
        self.cell_function = cell_function

    def run(self, jobs: Sequence[CellJob]) -> Iterator[Finished]:
        for job in jobs:
            yield job, self.cell_function(job), True

    def close(self) -> None:
        pass


def _ray():
    try:
        import ray
    except ImportError as e:
        raise CampaignError("Ray is not installed: `make setup` installs it (the campaign "
                            "extra of pyproject.toml), or use --serial") from e
    return ray


class RayExecutor:
    """Cells as Ray tasks (one CPU each), at most ``2 x workers`` in flight.

    Args:
        address: None starts a local Ray; ``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``
            joins that cluster.
        workers: local Ray's CPUs (default: this machine's cores); on a cluster the
            limit of cells running at once (default: the cluster's CPUs).
    """

    def __init__(self, address: str | None = None, workers: int | None = None,
                 cell_function: Callable[[CellJob], dict[str, Any]] = run_cell) -> None:
        ray = _ray()
        self.ray = ray
        # No usage statistics (they would leave the machine); keep 127.0.0.1 as given.
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        runtime_env = {"env_vars": dict(WORKER_ENV)}
        try:
            if address is None:
                cpus = workers or os.cpu_count() or 1
                ray.init(num_cpus=cpus, include_dashboard=False, _node_ip_address="127.0.0.1",
                         object_store_memory=LOCAL_OBJECT_STORE_BYTES, runtime_env=runtime_env,
                         log_to_driver=False, configure_logging=False)
                self.description = f"local Ray on 127.0.0.1, {cpus} workers"
            else:
                ray.init(address=address, runtime_env=runtime_env, log_to_driver=False,
                         configure_logging=False)
                cpus = int(ray.cluster_resources().get("CPU", 1))
                self.description = f"Ray cluster at {address}, {cpus} CPUs"
        except Exception as e:  # noqa: BLE001 - Ray raises many kinds: one message
            raise CampaignError(f"cannot start or reach Ray ({address or 'local'}): {e}") from e
        self.workers = max(1, workers or cpus)
        self.remote = ray.remote(num_cpus=1, max_retries=0)(cell_function)

    def run(self, jobs: Sequence[CellJob]) -> Iterator[Finished]:
        ray = self.ray
        pending = list(jobs)[::-1]
        in_flight: dict[Any, CellJob] = {}
        try:
            while pending or in_flight:
                while pending and len(in_flight) < 2 * self.workers:
                    job = pending.pop()
                    in_flight[self.remote.remote(job)] = job
                done, _ = ray.wait(list(in_flight), num_returns=1)
                for ref in done:
                    job = in_flight.pop(ref)
                    try:
                        yield job, ray.get(ref), True
                    except ray.exceptions.RayError as e:  # the worker died, not the run
                        yield job, {"key": job.key, "completed": 0, "end_reason": "error",
                                    "error": f"{type(e).__name__}: {str(e).splitlines()[0]}"}, False
        finally:
            for ref in in_flight:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        self.ray.shutdown()


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


def run_campaign(grid: Grid, out_dir: Path, executor: Any, *, progress: bool = True,
                 on_row: Callable[[dict[str, Any]], None] | None = None) -> CampaignResult:
    """Run every cell of ``grid`` not yet cached in ``out_dir``; a KeyboardInterrupt stops
    the campaign and returns what finished (``interrupted`` True)."""
    from tqdm import tqdm

    started = time.monotonic()
    cache = Cache(out_dir)
    version = code_version()
    jobs = [cell_job(grid, cell, version) for cell in grid.cells]
    axes = {job.key: effective_values(grid.scenario_document(cell), cell)
            for cell, job in zip(grid.cells, jobs)}
    results: dict[str, dict[str, Any]] = {}
    for job in jobs:
        cached = cache.get(job.key)
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
    stream = executor.run(todo)
    try:
        for job, row, keep in stream:
            row = {**axes[job.key], **row}
            if keep:
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


def finished_rows(rows: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of cells that ran (completed or not) without an error."""
    return [r for r in rows if not r.get("error")]

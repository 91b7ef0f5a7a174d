"""Trained rows' models (``fit = "train"`` of ``studies.campaign.prediction_rows``): trained
once, cached as artefacts in a folder and taken from there.

A model is cached as ``FOLDER/<label slug>_s<seed>.npz`` (its ``.json`` beside it) and taken
when its JSON records the same data hash, training settings and states; the committed
default artefact (``models/artifacts/dk_d5``) is taken first where it matches (Table I's
default row, seed 0). ``make table1``'s cells (``studies.campaign.prediction_cell``) train
through :func:`train_and_cache`; :func:`train_missing` trains a list of rows and seeds as
executor tasks without evaluating them (``studies.step_steer_spread``'s variants).
torch is imported only while training.
"""
from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from models.koopman import DEFAULT_ARTIFACT, KoopmanError, KoopmanModel
from models.koopman_metrics import Trajectory
from models.local_lateral_fit import friction_of_runs
from studies.campaign.prediction_rows import TS, WHEEL_STATES, Row, settings_of


def _slug(label: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", label.lower()).strip("_")


def cached_model_path(row: Row, seed: int, models_dir: Path) -> Path:
    """Where ``row``'s model of ``seed`` is cached (``.npz``, its ``.json`` beside it)."""
    return models_dir / f"{_slug(row.label)}_s{seed}.npz"


def cached_model(row: Row, seed: int, data_hash: str, models_dir: Path) -> KoopmanModel | None:
    """The row's model for ``seed`` when a matching cached (or the committed) artefact
    exists: same data hash, training settings and states; else None."""
    from models import koopman_train  # torch is needed here only

    wanted = koopman_train.settings_json(settings_of(row, seed))
    for candidate in (DEFAULT_ARTIFACT, cached_model_path(row, seed, models_dir)):
        json_path = candidate.with_suffix(".json")
        if candidate.is_file() and json_path.is_file():
            meta = json.loads(json_path.read_text())
            if (meta.get("data_hash") == data_hash and meta.get("settings") == wanted
                    and tuple(meta.get("state_names", ())) == row.states):
                return KoopmanModel.load(candidate)
    return None


def train_and_cache(row: Row, seed: int, data_dir: Path, data_hash: str, models_dir: Path) -> tuple[Path, float]:
    """Train ``row`` with ``seed`` on the data set in ``data_dir`` (whose hash must be
    ``data_hash``) and cache the artefact in ``models_dir``; returns (path, seconds).

    Raises:
        KoopmanError: the data set's hash differs (it changed since the table started);
            the trainer's own errors.
    """
    from models import koopman_train  # torch is needed here only

    runs = koopman_train.load_trajectories(data_dir, states=WHEEL_STATES)
    if koopman_train.dataset_hash(data_dir) != data_hash:
        raise KoopmanError(f"{data_dir} differs from the data set the table was started on")
    own = [Trajectory(r.name, r.states[:, : len(row.states)], r.inputs, row.states, r.input_names) for r in runs]
    result = koopman_train.train(own, TS, settings_of(row, seed), metadata={
        "data_dir": str(data_dir), "data_hash": data_hash, "n_runs": len(runs)}, progress=False,
        friction=friction_of_runs(data_dir))
    path = cached_model_path(row, seed, models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    koopman_train.write_artifact(result, path.with_suffix(""))
    return path, result.seconds


@dataclass(frozen=True)
class TrainingTask:
    """One training for a worker (picklable): ``row`` with ``seed`` on the data set in
    ``data_dir`` (whose hash is ``data_hash``), written into ``models_dir``."""

    key: str
    row: Row
    seed: int
    data_dir: Path
    data_hash: str
    models_dir: Path


def train_task(task: TrainingTask) -> dict[str, Any]:
    """Train and cache one model (a Ray task or in this process); never raises.

    Returns {path, seconds} or {error}. The worker reads the data set itself, so on a
    cluster every node needs it at the same path (docs/campaign.md).
    """
    try:
        path, seconds = train_and_cache(task.row, task.seed, task.data_dir, task.data_hash, task.models_dir)
    except Exception as e:  # noqa: BLE001 - reported as this training's failure
        return {"error": f"{type(e).__name__}: {e}"}
    return {"path": str(path), "seconds": seconds}


def train_missing(rows: Sequence[Row], seeds: Sequence[int], data_dir: Path, data_hash: str,
                  models_dir: Path, executor_options: dict[str, Any] | None = None) -> None:
    """Train every (row, seed) without a cached model, as tasks of the campaigns' executors
    (``studies.campaign.executors``: a local Ray by default, a cluster by address, or this
    process with ``serial``). Raises KoopmanError naming every training that failed."""
    from tqdm import tqdm

    from studies.campaign.executors import open_executor

    tasks = [TrainingTask(f"{row.label} seed {seed}", row, seed, data_dir, data_hash, models_dir)
             for seed in seeds for row in rows if cached_model(row, seed, data_hash, models_dir) is None]
    if not tasks:
        return
    print(f"training {len(tasks)} models", file=sys.stderr, flush=True)
    executor = open_executor(train_task, **(executor_options or {}))
    failures = []
    try:
        with tqdm(total=len(tasks), desc="trainings", unit="model", dynamic_ncols=True) as bar:
            for task, outcome, worker_error in executor.run(tasks):
                error = worker_error or (outcome or {}).get("error")
                if error:
                    failures.append(f"{task.key}: {error}")
                else:
                    print(f"{task.key}: trained in {outcome['seconds']:.0f} s -> {outcome['path']}",
                          file=sys.stderr, flush=True)
                bar.update(1)
    finally:
        executor.close()
    if failures:
        raise KoopmanError("trainings failed (the others are cached): " + "; ".join(failures))

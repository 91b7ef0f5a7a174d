"""A campaign cell on the ``prediction`` runner (Table I, ``make table1``): one model row x
one seed. The worker splits the data set by run as the trainer does for the seed, trains the
row's model (or takes it from the campaign folder, ``prediction_training``) or fits it
(``prediction_rows.fit_closed_form``), and measures its prediction errors on the seed's
held-out test runs.

:func:`run_prediction_cell` is the executors' task (a Ray worker, or this process): it takes
a :class:`PredictionJob` (plain data) and never raises for a failure of the cell: the error
is in the row (``error``, ``end_reason`` "error"), as a scenario cell's.

Row fields: ``figures`` ({state: {one_step_rmse, 1 s, 2 s}}, ``prediction_rows.evaluate``),
``rho`` (largest spectral radius of the lifted A; None for a physics model), ``note``,
``epochs`` (``best/run``; None without training), ``horizon_rmse`` (RMSE per prediction step,
40 x 3), ``trace`` (one-step errors along the seed's first test run, (len - 1) x 3) and
``trace_run`` (that run's name); ``completed`` (1 / 0), ``end_reason`` (``measured`` or
``error``), ``error``, ``wall_s``.

Cache key (:func:`prediction_job`): the row (label, fit, settings overrides, states), the
seed, the data set's hash and the code version of this module and everything it imports
(``studies.campaign.runner.code_version`` with :data:`PREDICTION_MODULES`), not the folder:
a rerun with the same code and data takes the cached cell. A trained model is cached apart
(by data hash, settings and states), so new code re-measures a row without training it again.
"""
from __future__ import annotations

import hashlib
import json
import time
import traceback
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from models.koopman import KoopmanError
from studies.campaign.prediction_rows import (TRAIN_FIT, WHEEL_STATES, Fitted, Row, evaluate, fit_closed_form,
                                              fitted_model, horizon_curve, one_step_trace)

#: Modules whose sources (and their imports') make a prediction cell's row.
PREDICTION_MODULES = ("studies.campaign.prediction_cell",)
#: Data files a prediction cell reads besides the data set (the committed default artefact
#: is the default row's seed 0 where it matches; the physics rows' parameters).
PREDICTION_DATA_FILES = ("models/vehicle.toml", "models/artifacts/dk_d5.npz", "models/artifacts/dk_d5.json")
#: Bump when what a cell computes changes in a way the key's other parts do not show.
PREDICTION_CACHE_VERSION = 1


@dataclass(frozen=True)
class PredictionJob:
    """What a worker needs for one cell: the row, the seed, the data set (``data_dir`` as
    the driver names it, its ``data_hash``) and the folder of the trained models."""

    key: str
    row: Row
    seed: int
    data_dir: str
    data_hash: str
    models_dir: str
    cacheable: bool = True
    exclusive: bool = False


def prediction_job(grid: Any, cell: Any, version: str, out_dir: Path, data_hash: str) -> PredictionJob:
    """The worker's job for ``cell`` of the ``prediction`` grid ``grid`` (module docstring
    for its key); trained models go to ``out_dir``."""
    row = grid.rows[cell.row]
    material = json.dumps({"version": PREDICTION_CACHE_VERSION, "runner": cell.runner, "seed": cell.seed,
                           "row": {"label": row.label, "fit": row.fit, "overrides": row.overrides,
                                   "states": list(row.states)},
                           "data_hash": data_hash, "code": version}, sort_keys=True)
    key = hashlib.sha256(material.encode()).hexdigest()[:24]
    return PredictionJob(key=key, row=row, seed=cell.seed, data_dir=str(grid.data_dir), data_hash=data_hash,
                         models_dir=str(out_dir))


@lru_cache(maxsize=1)
def _runs(data_dir: str, data_hash: str) -> tuple[Any, ...]:
    """The data set's runs with :data:`WHEEL_STATES`, loaded once per process and data set."""
    from models.koopman_data import dataset_hash, load_trajectories

    if dataset_hash(Path(data_dir)) != data_hash:
        raise KoopmanError(f"{data_dir} differs from the data set the table was started on")
    return tuple(load_trajectories(Path(data_dir), states=WHEEL_STATES))


def fit_row(row: Row, seed: int, data_dir: Path, data_hash: str, models_dir: Path) -> tuple[Fitted, list, Any]:
    """The row's predictor for ``seed`` (a trained row: its cached model, trained first when
    missing), with the seed's test runs and the data's runs.

    Raises:
        KoopmanError: the data set changed, or a model's test runs differ from the split.
    """
    from models.koopman_data import split_runs
    from models.koopman_settings import TrainingSettings

    runs = list(_runs(str(data_dir), data_hash))
    train_runs, _, test_runs = split_runs(runs, TrainingSettings(seed=seed))
    if row.fit != TRAIN_FIT:
        return fit_closed_form(row, seed, runs, train_runs, test_runs), test_runs, runs
    from studies.campaign.prediction_training import cached_model, train_and_cache

    model = cached_model(row, seed, data_hash, models_dir)
    if model is None:
        train_and_cache(row, seed, data_dir, data_hash, models_dir)
        model = cached_model(row, seed, data_hash, models_dir)
    if model is None:
        raise KoopmanError(f"{row.label} seed {seed}: no model after training; delete {models_dir}")
    return fitted_model(row, seed, model, test_runs), test_runs, runs


def run_prediction_cell(job: PredictionJob) -> dict[str, Any]:
    """Measure one cell (module docstring for the row)."""
    started = time.perf_counter()
    row: dict[str, Any] = {"key": job.key, "completed": 0, "end_reason": "error", "error": ""}
    try:
        fitted, test_runs, _ = fit_row(job.row, job.seed, Path(job.data_dir), job.data_hash, Path(job.models_dir))
        row.update(figures=evaluate(fitted.predictor, test_runs), rho=fitted.rho, note=fitted.note,
                   epochs=fitted.epochs, horizon_rmse=horizon_curve(fitted.predictor, test_runs).tolist(),
                   trace=one_step_trace(fitted.predictor, test_runs[0]).tolist(), trace_run=test_runs[0].name,
                   completed=1, end_reason="measured")
    except Exception as e:  # noqa: BLE001 - recorded in the row; the campaign goes on
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc(limit=8)
    row["wall_s"] = time.perf_counter() - started
    return row

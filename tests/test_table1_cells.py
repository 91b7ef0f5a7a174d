"""Table I on the campaign engine (the ``prediction`` runner, the grids ``table1`` and
``table1_smoke``, ``studies.table1``): a row x seed cell is, to the last bit, what Table I
measured before it ran on the engine (the model trained by ``models.koopman_train.train``,
written and loaded, or fitted by ``fit_least_squares``, evaluated on the seed's test runs),
and a rerun with the same code and data takes the cached cells.

The smoke check (a tiny training and edmdc-linear, two seeds, 4 cells; about 30 s)::

    .venv/bin/python -m pytest -q tests/test_table1_cells.py -k smoke -s
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from models.data import generate_dataset  # noqa: E402
from models.koopman import KoopmanModel  # noqa: E402
from models.koopman_data import dataset_hash, load_trajectories, split_runs  # noqa: E402
from models.koopman_metrics import Trajectory  # noqa: E402
from models.koopman_settings import TrainingSettings  # noqa: E402
from models.lifted_least_squares import fit_least_squares  # noqa: E402
from models.local_lateral_fit import friction_of_runs  # noqa: E402
from studies.campaign.executors import SerialExecutor  # noqa: E402
from studies.campaign.grid import GridError, load_grid  # noqa: E402
from studies.campaign.prediction_cell import run_prediction_cell  # noqa: E402
from studies.campaign.runner import campaign_jobs, run_campaign  # noqa: E402
from studies.table1 import (CLOSED_FORM_ROWS, DEFAULT_ROW, ROWS, TS, WHEEL_STATES, VehicleStates, evaluate,  # noqa: E402
                            horizon_curve, measure_rows, table1_grid)

ROOT = Path(__file__).resolve().parent.parent
VEHICLE = ("vx", "vy", "yaw_rate")
SYMMETRIC = {"mirror_symmetric": True, "n_features": 8, "even_features": 2, "servo_lag": True, "steer_bilinear": True}
#: Table I's rows as studies/table1.py held them before the grid (labels, overrides, states):
#: the grid must give the same, or build/table1's trained models would not be found again
#: (the last three rows, the vy anchor's and the physics dictionary's, added since).
ROWS_BEFORE = [
    ("DK scheduled + wheel angle, d=5", {}, WHEEL_STATES),
    ("DK scheduled, d=5", {}, VEHICLE),
    ("DK bilinear + dictionary, d=5", {"form": "bilinear"}, VEHICLE),
    ("DK paper form (linear), d=5", {"form": "linear", "dictionary": ()}, VEHICLE),
    ("mirror-symmetric, d=8 (2 even), servo lag, steer-bilinear N(v)", SYMMETRIC, WHEEL_STATES),
    ("mirror-symmetric steer-bilinear + gain anchor (w = 10) (default)", {**SYMMETRIC, "gain_anchor": 10.0},
     WHEEL_STATES),
    ("mirror-symmetric steer-bilinear + gain anchor (w = 10) + vy anchor (w = 10)",
     {**SYMMETRIC, "gain_anchor": 10.0, "gain_anchor_vy": 10.0}, WHEEL_STATES),
    ("mirror-symmetric, d=12 (3 even), physics dictionary, servo lag, steer-bilinear N(v)",
     {**SYMMETRIC, "n_features": 12, "even_features": 3, "dictionary": ("vy/vx", "r/vx", "vx*r", "vx^2/100")},
     WHEEL_STATES),
    ("mirror-symmetric, d=12 (3 even), physics dictionary + gain anchor (w = 10)",
     {**SYMMETRIC, "n_features": 12, "even_features": 3, "gain_anchor": 10.0,
      "dictionary": ("vy/vx", "r/vx", "vx*r", "vx^2/100")}, WHEEL_STATES),
    ("mirror-symmetric, d=12 (3 even), physics dictionary + gain anchor (w = 1)",
     {**SYMMETRIC, "n_features": 12, "even_features": 3, "gain_anchor": 1.0,
      "dictionary": ("vy/vx", "r/vx", "vx*r", "vx^2/100")}, WHEEL_STATES),
    ("mirror-symmetric, d=12 (3 even), physics dictionary without vx^2 + gain anchor (w = 1)",
     {**SYMMETRIC, "n_features": 12, "even_features": 3, "gain_anchor": 1.0,
      "dictionary": ("vy/vx", "r/vx", "vx*r")}, WHEEL_STATES),
]
CLOSED_FORM_BEFORE = ["DMDc", "EDMDc", "EDMDc physics dictionary, linear (edmdc-linear)",
                      "EDMDc physics dictionary, bilinear (edmdc-bilinear)", "linear bicycle (LMPC)",
                      "single track (NMPC)"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wide")
    generate_dataset(out, hours=0.05, seed=5, progress=False, profile="wide")
    return out


def _direct(row, seed: int, data_dir: Path, folder: Path) -> tuple[dict, float | None, str | None, np.ndarray]:
    """Table I's measurement of one row and seed before the engine: figures, rho, epochs,
    the RMSE per prediction step."""
    from models import koopman_train

    runs = load_trajectories(data_dir, states=WHEEL_STATES)
    _, _, test_runs = split_runs(runs, TrainingSettings(seed=seed))
    if row.fit == "train":
        own = [Trajectory(r.name, r.states[:, : len(row.states)], r.inputs, row.states, r.input_names) for r in runs]
        result = koopman_train.train(own, TS, TrainingSettings(**{**row.overrides, "seed": seed}), metadata={
            "data_dir": str(data_dir), "data_hash": dataset_hash(data_dir), "n_runs": len(runs)}, progress=False,
            friction=friction_of_runs(data_dir))
        koopman_train.write_artifact(result, folder / f"direct_s{seed}")
        model = KoopmanModel.load(folder / f"direct_s{seed}.npz")
        predictor, epochs = VehicleStates(model, len(row.states)), \
            f"{model.metadata['best_epoch']}/{model.metadata['epochs_run']}"
    else:
        model = fit_least_squares(runs, TS, row.fit, TrainingSettings(seed=seed)).model
        predictor, epochs = VehicleStates(model, len(model.state_names)), None
    return evaluate(predictor, test_runs), model.spectral_radius(), epochs, horizon_curve(predictor, test_runs)


@pytest.mark.slow
def test_smoke_grid_cells_equal_the_direct_path_bit_for_bit(data_dir: Path, tmp_path: Path) -> None:
    """The grid table1_smoke on the engine (in this process, then again from its cache), as
    studies.table1 gathers it, against the direct trainings and fits of the same rows."""
    grid = dataclasses.replace(table1_grid("table1_smoke"), data_dir=data_dir)
    assert len(grid.cells) == 4 and {row.fit for row in grid.rows.values()} == {"train", "edmdc-linear"}
    first = run_campaign(grid, tmp_path / "engine", SerialExecutor(run_prediction_cell), progress=False)
    again = run_campaign(grid, tmp_path / "engine", SerialExecutor(run_prediction_cell), progress=False)
    assert (first.computed, first.failed, again.computed, again.cached) == (4, 0, 0, 4)
    assert again.rows == first.rows
    trained = [row for row in grid.rows.values() if row.fit == "train"]
    seeds = [0, 1]
    table = measure_rows(data_dir, trained, seeds, tmp_path / "engine", {"serial": True}, grid=grid)
    assert [row["label"] for row in table.rows] == list(grid.rows)
    worst = 0.0
    for entry in table.rows:
        row = grid.rows[entry["label"]]
        for k, seed in enumerate(seeds):
            figures, rho, epochs, curve = _direct(row, seed, data_dir, tmp_path)
            worst = max([worst, *(abs(entry["seeds"][k][s][h] - figures[s][h]) for s in figures for h in figures[s])])
            assert entry["seeds"][k] == figures, (row.label, seed)
            assert entry["rho"][k] == rho and (epochs is None or entry["epochs"][k] == epochs)
            cell = next(c for c in first.rows if (c["row"], c["seed"]) == (row.label, seed))
            assert np.array_equal(np.asarray(cell["horizon_rmse"]), curve)
    print(f"max |engine - direct| over every figure of every cell: {worst:.1e}")
    assert set(table.traces) == {row.label for row in trained}
    assert table.traces[trained[0].label].shape == (len(table.trace_run) - 1, 3)


def test_table1_grid_holds_the_rows_and_seeds_table1_had() -> None:
    assert [(row.label, row.overrides, row.states) for row in ROWS] == ROWS_BEFORE
    assert {row.fit for row in ROWS} == {"train"} and DEFAULT_ROW is ROWS[5]
    assert [row.label for row in CLOSED_FORM_ROWS] == CLOSED_FORM_BEFORE
    grid = load_grid("table1")
    assert len(grid.cells) == 17 * 5 and sorted({c.seed for c in grid.cells}) == [0, 1, 2, 3, 4]


def test_cell_keys_name_row_seed_and_data(data_dir: Path, tmp_path: Path) -> None:
    grid = dataclasses.replace(table1_grid("table1_smoke"), data_dir=data_dir)
    keys = [job.key for job in campaign_jobs(grid, tmp_path, "code-1")]
    assert len(set(keys)) == 4
    assert keys == [job.key for job in campaign_jobs(grid, tmp_path / "elsewhere", "code-1")]  # not the folder
    assert not set(keys) & {job.key for job in campaign_jobs(grid, tmp_path, "code-2")}
    tiny = next(iter(grid.rows.values()))
    other = grid.with_rows([dataclasses.replace(tiny, overrides={**tiny.overrides, "max_epochs": 3})], [0])
    assert campaign_jobs(other, tmp_path, "code-1")[0].key not in keys


def test_grid_refuses_bad_prediction_tables(tmp_path: Path) -> None:
    base = (ROOT / "studies/campaign/grids/table1_smoke.toml").read_text()
    cases = {
        "unknown fit": (base.replace('fit = "edmdc-linear"', 'fit = "edmdc-cubic"'), "fit"),
        "no such setting": (base.replace("threads = 1", "threads = 1, depth = 3"), "settings.depth"),
        "seed in settings": (base.replace("threads = 1", "threads = 1, seed = 3"), "settings.seed"),
        "bad setting": (base.replace("max_epochs = 2", "max_epochs = -2"), "settings"),
        "settings of a physics row": (base.replace('fit = "edmdc-linear"', 'fit = "bicycle"\nsettings = { seq_len = 4 }'),
                                      "takes no training settings"),
        "bad states": (base.replace('states = ["vx", "vy", "yaw_rate"]', 'states = ["vy", "vx", "yaw_rate"]'), "states"),
        "unknown row": (base.replace("seed = [0, 1]", 'seed = [0, 1]\nrow = ["nothing"]'), "axes.row"),
        "mixed runner": (base.replace('runner = "prediction"', 'runner = ["prediction", "hil"]'), "stands alone"),
        "scenario axis": (base.replace("seed = [0, 1]", 'seed = [0, 1]\nscenario = ["dlc_smoke"]'), "axes.scenario"),
        "bad seed": (base.replace("seed = [0, 1]", "seed = [0, -1]"), "axes.seed"),
    }
    for name, (text, named) in cases.items():
        file = tmp_path / "grid.toml"
        file.write_text(text)
        with pytest.raises(GridError, match=named):
            load_grid(file)
        print(f"{name}: refused")


def test_a_failed_cell_is_named_in_its_row(data_dir: Path, tmp_path: Path) -> None:
    """A cell whose data set changed after the jobs were made: its row holds the error."""
    grid = dataclasses.replace(table1_grid("table1_smoke"), data_dir=data_dir)
    job = dataclasses.replace(campaign_jobs(grid, tmp_path, "v")[2], data_hash="sha256:not-this-data")
    row = run_prediction_cell(job)
    assert row["completed"] == 0 and row["end_reason"] == "error" and "differs from the data set" in row["error"]

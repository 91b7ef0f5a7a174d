"""Table I's least-squares rows (studies/table1.py) and its rows without training alone
(studies/table1_least_squares.py, ``make table1-lsq``): the edmdc-* rows are the trainer's
own fit, run for run; the report names the seeds, where the deep rows are, whether Table I's
JSON is listed stale, and sets the best least-squares row beside the deep default."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.data import generate_dataset
from models.koopman import KoopmanModel
from models.koopman_cli import main as train_main
from models.koopman_data import load_trajectories, split_runs
from models.koopman_settings import TrainingSettings
from studies.campaign.prediction_rows import fit_closed_form
from studies.table1 import (CLOSED_FORM_ROWS, DEFAULT_ROW, FITTED_ROWS, LEAST_SQUARES_ROWS, WHEEL_STATES,
                            VehicleStates, evaluate)
from studies.table1_least_squares import main

CLOSED_FORM_LABELS = ["DMDc", "EDMDc", *LEAST_SQUARES_ROWS, "linear bicycle (LMPC)", "single track (NMPC)"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wide")
    generate_dataset(out, hours=0.1, seed=5, progress=False, profile="wide")
    return out


@pytest.mark.parametrize("form", sorted(LEAST_SQUARES_ROWS.values()))
def test_the_least_squares_rows_are_the_trainers_fit(data_dir: Path, tmp_path: Path, form: str) -> None:
    """The row of seed 1 and ``python -m models.koopman_train --form FORM --seed 1``: the same
    test runs and the same figures."""
    seed = 1
    runs = load_trajectories(data_dir, states=WHEEL_STATES)
    train_runs, _, test_runs = split_runs(runs, TrainingSettings(seed=seed))
    row = next(row for row in CLOSED_FORM_ROWS if row.fit == form)
    row_predictor = fit_closed_form(row, seed, runs, train_runs, test_runs).predictor
    assert train_main(["--data", str(data_dir), "--form", form, "--seed", str(seed), "--out", str(tmp_path / "m"),
                       "--no-progress"]) == 0
    trained = KoopmanModel.load(tmp_path / "m")
    assert trained.metadata["split"]["test"] == [r.name for r in test_runs]
    ours, theirs = evaluate(row_predictor, test_runs), evaluate(VehicleStates(trained, len(WHEEL_STATES)), test_runs)
    difference = max(abs(ours[s][h] - theirs[s][h]) / theirs[s][h] for s in ours for h in ours[s])
    print(f"largest relative difference of the row's figures to the trainer's model: {difference:.1e}")
    assert difference < 1e-9


def _table1(folder: Path, seeds: list[int], data_hash: str = "sha256:other") -> Path:
    """A Table I JSON with the deep default row (RMSE 0.1 of every figure, 0.1 + 0.01 seed),
    listed stale in KNOWN_STALE.md beside it."""
    folder.mkdir()
    figures = [{s: {"one_step_rmse": 0.01, "1 s": 0.1 + 0.01 * k, "2 s": 0.1 + 0.01 * k}
                for s in ("vx", "vy", "yaw_rate")} for k in range(len(seeds))]
    path = folder / "table1.json"
    path.write_text(json.dumps({"data_hash": data_hash, "data_dir": "data/wide", "seeds": seeds, "rows": [
        {"label": DEFAULT_ROW.label, "seeds": figures, "rho": [1.0], "epochs": [], "note": "", "seed_ids": seeds}]}))
    (folder / "KNOWN_STALE.md").write_text(
        "Text.\n\n| Files | Regenerates them | Why not regenerated yet |\n|---|---|---|\n"
        f"| `{folder.name}/table1.json`, `{folder.name}/table1.md` | `make table1` | inputs moved by rounding only |\n")
    return path


def test_the_report_sets_the_best_least_squares_row_beside_the_deep_default(data_dir: Path, tmp_path: Path,
                                                                            capsys) -> None:
    table1 = _table1(tmp_path / "results", [0, 1])
    out = tmp_path / "out"
    assert main(["--data", str(data_dir), "--seeds", "0,1", "--out", str(out), "--table1", str(table1),
                 "--models-dir", str(tmp_path / "cells")]) == 0
    report = (out / "table1_least_squares.md").read_text()
    saved = json.loads((out / "table1_least_squares.json").read_text())
    assert [row["label"] for row in saved["rows"]] == CLOSED_FORM_LABELS
    assert saved["seeds"] == [0, 1] and all(row["seed_ids"] == [0, 1] for row in saved["rows"])
    assert "Seeds 0, 1 " in report and f"`{table1.with_suffix('.md')}`" in report
    assert "listed stale" in report and "inputs moved by rounding only" in report
    assert "was measured on data sha256:other" in report
    versus = saved["versus_deep"]
    assert versus["known_stale"] == "inputs moved by rounding only" and versus["same_seeds"]
    assert [(c["state"], c["horizon"]) for c in versus["cells"]] == [
        ("vy", "1 s"), ("vy", "2 s"), ("yaw_rate", "1 s"), ("yaw_rate", "2 s")]
    for cell in versus["cells"]:
        fitted = [row for row in saved["rows"] if row["label"] in FITTED_ROWS]
        means = {row["label"]: np.mean([f[cell["state"]][cell["horizon"]] for f in row["seeds"]]) for row in fitted}
        assert cell["best_least_squares"] == min(means, key=means.get)
        assert cell["least_squares_mean"] == pytest.approx(means[cell["best_least_squares"]])
        assert cell["deep_mean"] == pytest.approx(0.105)
        assert cell["deep_over_least_squares"] == pytest.approx(0.105 / cell["least_squares_mean"])
    assert "| vy | 1 s |" in capsys.readouterr().out


def test_without_table1_the_report_says_there_is_no_comparison(data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["--data", str(data_dir), "--seeds", "0", "--out", str(out),
                 "--table1", str(tmp_path / "absent" / "table1.json"), "--models-dir", str(tmp_path / "cells")]) == 0
    report = (out / "table1_least_squares.md").read_text()
    assert "No comparison:" in report and "not found" in report


def test_a_missing_data_set_is_one_error_line(tmp_path: Path, capsys) -> None:
    assert main(["--data", str(tmp_path / "none"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: data directory not found") and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


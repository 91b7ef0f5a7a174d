"""Table I's trainings as executor tasks: missing models trained and cached, then reused;
a failed training named; the same code path on Ray as in this process."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("torch")

from models.data import generate_dataset  # noqa: E402
from models.errors import ModelError  # noqa: E402
from models.koopman_train import dataset_hash  # noqa: E402
from studies.table1 import VEHICLE_STATES, Row, cached_model, cached_model_path, train_missing  # noqa: E402

#: A tiny training: a few epochs of a small net, enough to write a real artefact.
TINY = {"n_features": 2, "hidden": (8, 8), "seq_len": 4, "batch_size": 16, "max_epochs": 2,
        "steps_per_epoch": 4, "patience": 2, "val_windows": 64, "threads": 1}
ROWS = (Row("tiny scheduled", dict(TINY), VEHICLE_STATES),
        Row("tiny linear", {**TINY, "form": "linear", "dictionary": ()}, VEHICLE_STATES))


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("data")
    generate_dataset(out, hours=0.04, seed=5, progress=False)
    return out


def test_missing_models_are_trained_once_then_reused(data_dir: Path, tmp_path: Path) -> None:
    digest = dataset_hash(data_dir)
    assert all(cached_model(row, 0, digest, tmp_path) is None for row in ROWS)
    train_missing(ROWS, (0,), data_dir, digest, tmp_path, {"serial": True})
    paths = [cached_model_path(row, 0, tmp_path) for row in ROWS]
    stamps = [p.stat().st_mtime_ns for p in paths]
    models = [cached_model(row, 0, digest, tmp_path) for row in ROWS]
    assert [m.form for m in models] == ["scheduled", "linear"]
    assert all(tuple(m.state_names) == VEHICLE_STATES for m in models)
    train_missing(ROWS, (0,), data_dir, digest, tmp_path, {"serial": True})  # nothing to do
    assert [p.stat().st_mtime_ns for p in paths] == stamps
    # Another seed is another model: only that one is trained.
    train_missing(ROWS[:1], (1,), data_dir, digest, tmp_path, {"serial": True})
    assert cached_model(ROWS[0], 1, digest, tmp_path) is not None
    assert [p.stat().st_mtime_ns for p in paths] == stamps


def test_a_failed_training_is_named_and_nothing_is_cached(data_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ModelError, match=r"tiny scheduled seed 0: .*differs from the data set"):
        train_missing(ROWS[:1], (0,), data_dir, "sha256:not-this-data", tmp_path, {"serial": True})
    assert not cached_model_path(ROWS[0], 0, tmp_path).exists()


@pytest.mark.slow
def test_trainings_run_as_ray_tasks(data_dir: Path, tmp_path: Path) -> None:
    pytest.importorskip("ray")
    digest = dataset_hash(data_dir)
    train_missing(ROWS, (0,), data_dir, digest, tmp_path, {"workers": 2})
    assert all(cached_model(row, 0, digest, tmp_path) is not None for row in ROWS)

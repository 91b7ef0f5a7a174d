"""The training smoke of ``python -m studies.restamp`` (studies/restamp_training.py): which
code it covers, and what counts as the same trained model."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from studies import restamp, restamp_training
from studies.restamp_training import artefact_difference, default_form, training_smoke, training_sources

ROOT = Path(__file__).resolve().parent.parent


def test_the_training_smoke_covers_the_trainer_and_the_data_generator_not_studies() -> None:
    covered = training_sources(ROOT)
    assert {"models/koopman_train.py", "models/koopman_cli.py", "models/koopman_train_anchor.py",
            "models/koopman_settings.py", "models/data.py"} <= covered
    assert not any(name.startswith("studies/") for name in covered)
    # what neither smoke runs: the loaders of CAN logs and mapped CSVs, --compare-with
    assert not restamp_training.NOT_TRAINED & (covered | restamp.smoke_sources(ROOT))
    assert "models/koopman_train.py" not in restamp.smoke_sources(ROOT)


def test_the_default_form_is_make_trains() -> None:
    form = default_form(ROOT)
    assert "--gain-anchor" in form and "--mirror-symmetric" in form


def test_a_makefile_without_the_form_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "mk").mkdir()
    (tmp_path / "mk" / "koopman.mk").write_text("TRAIN_DATA ?= data/wide\n")
    with pytest.raises(restamp_training.TrainingSmokeError, match="no KOOPMAN_FORM line"):
        default_form(tmp_path)


def _artefact(path: Path, weight: float = 1.0, seconds: float = 4.8, data_dir: str = "/a") -> Path:
    np.savez(path.with_suffix(".npz"), A=np.eye(3) * weight, B=np.ones((3, 2)))
    path.with_suffix(".json").write_text(json.dumps({"training_seconds": seconds, "data_dir": data_dir,
                                                     "best_epoch": 2, "settings": {"seed": 0}}))
    return path


def test_wall_clock_seconds_and_the_data_folder_are_not_behaviour(tmp_path: Path) -> None:
    base = _artefact(tmp_path / "base")
    assert artefact_difference(base, _artefact(tmp_path / "now", seconds=5.6, data_dir="/b")) is None


def test_a_changed_array_or_setting_is_named(tmp_path: Path) -> None:
    base = _artefact(tmp_path / "base")
    assert artefact_difference(base, _artefact(tmp_path / "w", weight=1.0 + 1e-16)) is None  # 1 + 1e-16 == 1
    assert artefact_difference(base, _artefact(tmp_path / "x", weight=1.0 + 1e-15)) == "x.npz: array A differs"
    other = _artefact(tmp_path / "y")
    meta = json.loads(other.with_suffix(".json").read_text())
    meta["settings"]["seed"] = 1
    other.with_suffix(".json").write_text(json.dumps(meta))
    assert artefact_difference(base, other) == "y.json: settings differ"


def _tree(tmp_path: Path, name: str) -> Path:
    """A copy of the trainer's code (models/, can_defs/ and the data they read) beside this
    checkout's virtual environment."""
    tree = tmp_path / name
    tree.mkdir()
    for folder in ("models", "can_defs", "controller", "hil", "mk"):
        shutil.copytree(ROOT / folder, tree / folder, ignore=shutil.ignore_patterns("__pycache__", "artifacts"))
    (tree / "models" / "artifacts").mkdir()
    (tree / ".venv").symlink_to((ROOT / ".venv").resolve())
    return tree


@pytest.mark.slow
def test_the_smoke_trains_alike_in_two_equal_trees_and_finds_changed_anchor_targets(tmp_path: Path) -> None:
    """About 75 s: the data set generated in the first tree, then two trainings on it in each
    of three trees."""
    form = default_form(ROOT)
    base, same, other = (_tree(tmp_path, name) for name in ("base", "same", "other"))
    anchor = other / "models" / "koopman_train_anchor.py"  # a step of 0.021 rad: other targets
    text = anchor.read_text()
    assert "\nANCHOR_STEP = 0.02 " in text
    anchor.write_text(text.replace("\nANCHOR_STEP = 0.02 ", "\nANCHOR_STEP = 0.021 ", 1))
    runs = {"base": training_smoke(base, tmp_path / "out-base", form, report=lambda _: None)}
    data = tmp_path / "out-base" / "data"
    assert (data / "READY").is_file()
    for tree in (same, other):
        runs[tree.name] = training_smoke(tree, tmp_path / f"out-{tree.name}", form, lambda _: None, data)
    assert [artefact_difference(a, b) for a, b in zip(runs["base"], runs["same"])] == [None, None]
    first, lsq = (artefact_difference(a, b) for a, b in zip(runs["base"], runs["other"]))
    assert first is not None and first.startswith("default.npz: array")
    assert lsq is None  # the least-squares lift has no anchor

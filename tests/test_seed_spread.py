"""The seed-spread study's table and its refusal to run without the seeds' models."""
from __future__ import annotations

from pathlib import Path

import pytest

from studies import seed_spread


def test_table_has_a_row_per_controller_and_scenario_with_mean_and_spread() -> None:
    run = {"completed": True, "e_y_rmse": 0.1, "e_y_max": 0.2}
    runs = {name: {s: [dict(run, e_y_rmse=0.1 + 0.1 * i) for i in range(3)] for s in seed_spread.SCENARIOS}
            for name in seed_spread.LEARNED}
    runs.update({name: {s: [dict(run, completed=False)] for s in seed_spread.SCENARIOS} for name in seed_spread.PHYSICS})
    text = seed_spread.markdown({"seeds": [0, 1, 2], "runs": runs})
    rows = [line for line in text.splitlines() if line.startswith("| eso-dkmpc") or line.startswith("| lmpc")]
    assert len(rows) == 4
    assert "0.200 ± 0.100" in text  # mean and sample sd of 0.1, 0.2, 0.3
    assert "0.100*" in text  # a run that did not complete is marked
    runs["dkmpc" + seed_spread.VY_ANCHOR] = runs["dkmpc"]
    anchored = seed_spread.markdown({"seeds": [0, 1, 2], "runs": runs})
    assert len([line for line in anchored.splitlines() if line.startswith("| dkmpc + vy anchor |")]) == 2
    runs["eso-dkmpc" + seed_spread.DICTIONARY] = runs["eso-dkmpc"]
    both = seed_spread.markdown({"seeds": [0, 1, 2], "runs": runs})
    assert len([line for line in both.splitlines() if line.startswith("| eso-dkmpc + dictionary, d=12 |")]) == 2
    runs["eso-dkmpc" + seed_spread.DICTIONARY_LIGHT_ANCHOR] = runs["eso-dkmpc"]
    light = seed_spread.markdown({"seeds": [0, 1, 2], "runs": runs})
    assert len([line for line in light.splitlines()
                if line.startswith("| eso-dkmpc + dictionary, d=12, anchor w=1 |")]) == 2
    assert len([line for line in light.splitlines() if line.startswith("| eso-dkmpc + dictionary, d=12 |")]) == 2
    runs["eso-dkmpc" + seed_spread.NO_SQUARE] = runs["eso-dkmpc"]
    square = seed_spread.markdown({"seeds": [0, 1, 2], "runs": runs})
    assert len([line for line in square.splitlines()
                if line.startswith("| eso-dkmpc + dictionary without vx^2, d=12, anchor w=1 |")]) == 2
    assert seed_spread.FORMS[-1][1] is seed_spread.DICTIONARY_NO_SQUARE_ROW


def test_missing_seed_models_name_the_command(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from hil.errors import StudyError

    with pytest.raises(StudyError, match="make table1"):
        seed_spread.seed_artifacts(tmp_path, (0, 1))
    # The anchored row has no committed artefact: its seed 0 comes from Table I's cache too.
    with pytest.raises(StudyError, match="vy anchor"):
        seed_spread.seed_artifacts(tmp_path, (0,), seed_spread.VY_ANCHOR_ROW)
    # --check-models names every missing model (the default row's seed 0 is the committed one)
    assert seed_spread.main(["--check-models", "--models-dir", str(tmp_path), "--seeds", "0,1"]) == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 * len(seed_spread.FORMS) - 1
    assert all(line.startswith("error: ") and "make table1" in line for line in lines)
    assert seed_spread.main(["--models-dir", str(tmp_path), "--seeds", "0,1"]) == 1

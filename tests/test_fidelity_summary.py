"""python -m studies.fidelity_summary: seeds of a training variant summarised from their
model_fidelity reports."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from studies import fidelity_summary

PLANT_VY = {10.0: 0.07, 15.0: 0.04, 20.0: -0.06, 25.0: -0.24}


def _report(vy_offset: dict[float, float], yaw_error: float, rmse_vy: float) -> dict:
    step = []
    for speed, vy in PLANT_VY.items():
        step.append({"speed": speed, "model": "plant", "yaw_rate": 0.1, "vy": vy, "yaw_error_pct": 0.0})
        step.append({"speed": speed, "model": "learned (scheduled)", "yaw_rate": 0.1, "vy": vy + vy_offset[speed],
                     "yaw_error_pct": yaw_error})
        step.append({"speed": speed, "model": "linear bicycle (LMPC)", "yaw_rate": 0.2, "vy": 0.0,
                     "yaw_error_pct": 50.0})
    prediction = [{"model": "learned (scheduled)", "horizon": h, "rmse": {"vx": 1.0, "vy": rmse_vy, "yaw_rate": 0.04}}
                  for h in ("1 s", "2 s")]
    prediction.append({"model": "linear bicycle (LMPC)", "horizon": "1 s", "rmse": {"vx": 9.0, "vy": 9.0, "yaw_rate": 9.0}})
    return {"step_steer": step, "prediction": prediction}


def _write(folder: Path, report: dict) -> None:
    folder.mkdir(parents=True)
    (folder / "model_fidelity.json").write_text(json.dumps(report))


def test_the_summary_counts_the_goals_per_seed_and_averages_the_learned_rows(tmp_path: Path,
                                                                             capsys: pytest.CaptureFixture[str]) -> None:
    within = {10.0: 0.005, 15.0: 0.0, 20.0: -0.003, 25.0: 0.02}  # 25 m/s: 8.3 % of 0.24
    beyond = {10.0: 0.02, 15.0: 0.0, 20.0: 0.0, 25.0: 0.0}  # 10 m/s: 0.02 m/s off
    _write(tmp_path / "f_s0", _report(within, 2.0, 0.10))
    _write(tmp_path / "f_s1", _report(beyond, -6.0, 0.20))
    (tmp_path / "f_s1.log").write_text("a log beside the folders is not a seed\n")
    table1 = tmp_path / "table1.json"
    table1.write_text(json.dumps({"rows": [{"label": "lift", "seeds": [
        {s: {"1 s": 0.3, "2 s": 0.3} for s in ("vy", "yaw_rate")}]}]}))
    assert fidelity_summary.main(["--group", f"w = 1={tmp_path}/f_s*", "--reference", "lift",
                                  "--table1", str(table1)]) == 0
    out = capsys.readouterr().out
    assert "| 1 s RMSE vy | 0.1500 ± 0.0707 (0.50 x) |" in out
    assert "| step-steer yaw rate within 5 % | 1 of 2 |" in out
    assert "| step-steer vy within issue 40's goal | 1 of 2 |" in out
    assert "- w = 1: +0.0050 / +0.0000 / -0.0030 / +0.0200; +0.0200 / +0.0000 / +0.0000 / +0.0000" in out


def test_bad_groups_and_references_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        fidelity_summary.main(["--group", f"x={tmp_path}/none*"])
    assert "give LABEL=GLOB matching model_fidelity output folders" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        fidelity_summary.main(["--group", f"x={tmp_path}/empty"])
    assert "no model_fidelity.json" in capsys.readouterr().err
    _write(tmp_path / "f", _report(dict.fromkeys(PLANT_VY, 0.0), 0.0, 0.1))
    table1 = tmp_path / "table1.json"
    table1.write_text(json.dumps({"rows": [{"label": "lift", "seeds": []}]}))
    with pytest.raises(SystemExit):
        fidelity_summary.main(["--group", f"x={tmp_path}/f", "--group", f"x={tmp_path}/f"])
    assert "--group 'x' given twice" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="not a row"):
        fidelity_summary.main(["--group", f"x={tmp_path}/f", "--reference", "nope", "--table1", str(table1)])

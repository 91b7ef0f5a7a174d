"""The pose-step study (studies/pose_step.py): its arc, its report's figures and its CLI's
refusal. The closed-loop property of the option itself (the midpoint stays on an arc, C
equals Python) is in tests/test_controller_qp.py and tests/test_firmware_c_actuator.py."""
from __future__ import annotations

import numpy as np
import pytest

from hil.scenario import load_scenario
from studies import pose_step
from studies.tuning_sweep_executor import Evaluation, objective


def _evaluation(name: str, advance: float | None, rmse: dict[str, float], completed: dict[str, bool]) -> Evaluation:
    setting = () if advance is None else pose_step.setting(advance)
    return Evaluation(controller=name, stage="pose-step", setting=setting, rmse_m=rmse,
                      max_abs_m={s: 2 * v for s, v in rmse.items()}, completed=completed,
                      failure={s: None if ok else "left the road" for s, ok in completed.items()},
                      objective_m=objective(rmse, completed), seconds=1.0)


def test_the_arc_of_the_curve_path() -> None:
    """straight_curve: 80 m straight, 25 m clothoid, the R 50 m arc, clothoid, straight."""
    progress = np.array([50.0, 95.0, 110.0, 130.0, 150.0, 170.0, 250.0])
    on_arc = pose_step.arc_mask(load_scenario(pose_step.CURVE_SCENARIO), progress)
    assert on_arc.tolist() == [False, False, True, True, True, False, False]


def test_report_figures() -> None:
    runs = ["a", "b", "c"]
    euler = _evaluation("dkmpc", 0.0, {"a": 0.02, "b": 0.04, "c": 0.03}, dict.fromkeys(runs, True))
    midpoint = _evaluation("dkmpc", 0.5, {"a": 0.01, "b": 0.05, "c": 0.02}, {"a": True, "b": True, "c": False})
    study = _evaluation("nmpc", None, {s: 0.015 for s in pose_step.STUDY_SCENARIOS},
                        dict.fromkeys(pose_step.STUDY_SCENARIOS, True))
    text, summary = pose_step.report([euler, midpoint], [study], {}, runs)
    # the midpoint's objective counts run c as the failure penalty: (0.01 + 0.05 + 10) / 3
    assert summary["tuning_set"]["dkmpc"]["objective_ratio"] == pytest.approx((10.06 / 3) / 0.03)
    assert summary["tuning_set"]["dkmpc"]["runs_lower_with_midpoint"] == 1  # a only; c did not complete
    assert "| c | 30.00 / - |" in text
    assert "| nmpc | - | 1.50 | 1.50 | 1.50 |" in text
    assert "seconds" not in summary["tuning_set"]["dkmpc"]["euler"]


def test_cli_refuses_no_workers(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        pose_step.main(["--workers", "0", "--out", "/nonexistent/never-written"])
    assert "--workers must be >= 1" in capsys.readouterr().err

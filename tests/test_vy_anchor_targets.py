"""The check of the vy anchor's targets against the plant (studies/vy_anchor_targets.py)."""
from __future__ import annotations

import pytest

from studies import vy_anchor_targets
from studies.model_fidelity import STEP_STEER, plant_step_steer


def test_the_plants_vy_is_the_antisymmetric_response_scaled_to_the_anchors_step() -> None:
    # at the step of model_fidelity's step steer, its plant run's final vy
    assert vy_anchor_targets.plant_final_vy(25.0, STEP_STEER) == plant_step_steer(25.0)[0][-1, 1]
    up, down = (vy_anchor_targets.plant_final_vy(25.0, s) for s in (0.02, -0.02))
    assert vy_anchor_targets.plant_vy(25.0, 0.02) == pytest.approx((up - down) / 2.0)
    # at 10 m/s the plant is linear in the step; at 25 m/s its vy grows faster than the step
    assert vy_anchor_targets.plant_vy(10.0, 0.005) == pytest.approx(vy_anchor_targets.plant_vy(10.0, 0.02), rel=0.01)
    assert abs(vy_anchor_targets.plant_vy(25.0, 0.02)) > 1.05 * abs(vy_anchor_targets.plant_vy(25.0, 0.005))


def test_the_table_gives_each_column_against_the_plants_step() -> None:
    row = {"speed": 25.0, "plant": -0.2, "plant_small": -0.18, "gentle": -0.19, "amplitude": -0.21,
           "grip_limit": 0.33, "target": -0.2, "gentle_target": -0.17}
    text = vy_anchor_targets.markdown([row], vy_anchor_targets.Path("data/wide"))
    assert "| 25 | -0.2000 | -0.1800 (-10.0 %) | -0.1900 (-5.0 %) | -0.2100 (+5.0 %) (0.33) | -0.2000 (+0.0 %) " \
           "| -0.1700 (-15.0 %) |" in text


def test_a_missing_data_set_is_named(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        vy_anchor_targets.main(["--data", "/nonexistent/data"])
    assert "--data /nonexistent/data: no such data set" in capsys.readouterr().err

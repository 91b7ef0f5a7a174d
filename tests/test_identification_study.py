"""The identification study's changed plant and its report (studies/identification.py);
the study itself is `make identify` (10-25 min), its results in results/identification/."""
from __future__ import annotations

import json

import pytest

from hil.scenario import load_scenario
from models.bicycle import nominal_model_params
from studies.identification import (CHANGED_LAG_FACTOR, CHANGED_MASS_OFFSET_KG, CHANGED_REAR_STIFFNESS_SCALE,
                                    bicycle_comparison, changed_params, tables_markdown,
                                    weighed_vehicle_file)


def test_changed_plant_is_heavier_has_softer_rear_tyres_and_its_steering_lags_three_times():
    nominal = load_scenario("dlc_low_mu").vehicle_params()
    changed = changed_params(nominal)
    assert changed.mass == pytest.approx(nominal.mass + CHANGED_MASS_OFFSET_KG)
    assert changed.steer_time_constant == pytest.approx(CHANGED_LAG_FACTOR * nominal.steer_time_constant)
    assert nominal.cornering_stiffness_rear_scale == 1.0
    assert changed.cornering_stiffness_rear_scale == CHANGED_REAR_STIFFNESS_SCALE == 0.8
    assert (changed.mu, changed.yaw_inertia, changed.cornering_stiffness_factor) == (
        nominal.mu, nominal.yaw_inertia, nominal.cornering_stiffness_factor)


def test_report_compares_the_fitted_bicycle_and_lists_every_run(tmp_path):
    nominal = nominal_model_params()
    (tmp_path / "bicycle.json").write_text(json.dumps({
        "kind": "linear_bicycle", "mass": nominal.mass + 300.0,
        "cornering_stiffness_front": 0.9 * nominal.cornering_stiffness_front,
        "cornering_stiffness_rear": nominal.cornering_stiffness_rear, "yaw_inertia": 1.1 * nominal.yaw_inertia}))
    bicycle = bicycle_comparison(tmp_path)
    assert bicycle["cornering_stiffness_front"]["change_percent"] == pytest.approx(-10.0)
    assert bicycle["yaw_inertia"]["change_percent"] == pytest.approx(10.0)
    assert bicycle["mass"]["fitted"] == nominal.mass + 300.0
    # The changed plant's own rear axle: about -20 %, less the extra load's degressive effect.
    rear = bicycle["cornering_stiffness_rear"]
    assert -21.0 < rear["plant_change_percent"] < -17.0
    assert rear["fit_error_percent"] == pytest.approx(100.0 * (1.0 / (1.0 + rear["plant_change_percent"] / 100.0) - 1.0),
                                                      abs=0.02)
    tracking = {"lateral_error_m": {"max_abs": 0.1, "mean_abs": 0.02, "rmse": 0.03},
                "heading_error_rad": {"max_abs": 0.01, "mean_abs": 0.002, "rmse": 0.003}}
    runs = [{"scenario": s, "controller": "LMPC, fitted bicycle, changed plant", "completed": True,
             "failure": None, "error": None, "tracking": tracking} for s in ("dlc_high_mu", "dlc_low_mu")]
    summary = {"bicycle": bicycle, "drive": {"controller": "dmdc-eso", "excitation": "prbs-torque",
                                             "frames_logged": 123},
               "servo": {"steps": 4321, "one_step_rmse_rad": 2.5e-4, "time_constant_s": 0.0901,
                         "nominal_time_constant_s": 0.03, "delay_compensation_s": 0.0601}}
    text = tables_markdown(runs, summary)
    print(text)
    assert "| cornering_stiffness_front |" in text and "| -10.0 % |" in text
    assert text.count("| LMPC, fitted bicycle, changed plant | yes | 0.100 / 0.020 / 0.030 |") == 2
    assert "rear tyres' cornering stiffness x0.8" in text
    # the servo fit and the delay compensation it gives are stated from the summary
    assert "time constant 90.1 ms against the nominal 30 ms" in text and "= 60 ms" in text
    # the stage times are the machine's: named where they are, never in the committed table
    assert "logs/identification_timing.json" in text and " s, total " not in text


def test_the_weighed_vehicle_file_differs_from_the_nominal_one_in_the_mass_only(tmp_path):
    from models.vehicle_params import load_vehicle_params, params_as_dict

    nominal = params_as_dict(load_vehicle_params())
    weighed = params_as_dict(load_vehicle_params(weighed_vehicle_file(tmp_path)))
    assert {k for k in nominal if nominal[k] != weighed[k]} == {"mass"}
    assert weighed["mass"] == nominal["mass"] + CHANGED_MASS_OFFSET_KG

"""Tuning file validation and the longitudinal P controller."""
from __future__ import annotations

import tomllib

import pytest

from controller.errors import TuningError
from controller.longitudinal import SpeedController
from controller.tuning import (DEFAULT_TUNING_PATH, LongitudinalTuning, StageWeights, load_tuning,
                               low_speed_twins, parse_tuning, with_fixed_weights)


def document() -> dict:
    with DEFAULT_TUNING_PATH.open("rb") as handle:
        return tomllib.load(handle)


def test_default_tuning_loads() -> None:
    tuning = load_tuning()
    for name in ("eso-dkmpc", "dkmpc", "lmpc", "nmpc"):
        table = tuning.for_controller(name)
        print(name, table.prediction_horizon, table.control_horizon)
        assert table.control_horizon <= table.prediction_horizon


@pytest.mark.parametrize(("table", "field", "value", "message"), [
    ("lmpc", "control_horizon", 40, "control_horizon (40) must be <= prediction_horizon (30)"),
    ("dkmpc", "r_steer", -1.0, "[dkmpc] r_steer must be > 0, got -1.0"),
    ("nmpc", "prediction_horizon", 2.5, "[nmpc] prediction_horizon must be an integer, got 2.5"),
    ("eso-dkmpc", "eso_pole", 1.2, "[eso-dkmpc] eso_pole must be in [0, 1), got 1.2"),
    ("eso-dkmpc", "eso_second_pole", -0.1, "[eso-dkmpc] eso_second_pole must be in [0, 1), got -0.1"),
    ("eso-dkmpc", "disturbance_decay", 1.5, "[eso-dkmpc] disturbance_decay must be in [0, 1], got 1.5"),
    ("eso-dkmpc", "state_max", [1.0, 2.0], "[eso-dkmpc] state_max must be a list of 3 finite numbers"),
    ("lmpc", "state_min", [0.0, 3.0, -1.0], "state_min[vy] (3.0) must be < state_max[vy] (2.0)"),
    ("lmpc", "weight_schedule_speeds", [15.0, 10.0],
     "[lmpc] weight_schedule_speeds must be two speeds 0 <= low < high (m/s), got [15.0, 10.0]"),
    ("nmpc", "weight_schedule_speeds", [10.0], "[nmpc] weight_schedule_speeds must be a list of 2 finite numbers"),
    ("dkmpc", "low_speed_r_steer", 0.0, "[dkmpc] low_speed_r_steer must be > 0, got 0.0"),
    ("longitudinal", "torque_min", 5000.0, "torque_min (5000.0) must be < torque_max"),
    ("longitudinal", "speed_gain", "fast", "[longitudinal] speed_gain must be a finite number, got 'fast'"),
])
def test_bad_values_name_field_and_value(table: str, field: str, value, message: str) -> None:
    doc = document()
    doc[table][field] = value
    with pytest.raises(TuningError) as error:
        parse_tuning(doc)
    print(error.value)
    assert message in str(error.value)


def test_missing_and_unknown_fields_and_tables() -> None:
    doc = document()
    del doc["lmpc"]["q_yaw"]
    with pytest.raises(TuningError, match=r"\[lmpc\] missing field\(s\) \['q_yaw'\]"):
        parse_tuning(doc)
    doc = document()
    doc["nmpc"]["q_jaw"] = 1.0
    with pytest.raises(TuningError, match=r"\[nmpc\] unknown field\(s\) \['q_jaw'\]"):
        parse_tuning(doc)
    doc = document()
    del doc["dkmpc"]
    with pytest.raises(TuningError, match=r"missing table\(s\) \['dkmpc'\]"):
        parse_tuning(doc)


def test_file_errors(tmp_path) -> None:
    with pytest.raises(TuningError, match="tuning file not found"):
        load_tuning(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[lmpc\n")
    with pytest.raises(TuningError, match="not valid TOML"):
        load_tuning(bad)


def test_speed_controller_is_proportional_and_clipped() -> None:
    controller = SpeedController(LongitudinalTuning(speed_gain=600.0, torque_min=-3000.0, torque_max=2000.0))
    torques = [controller.torque(vx, 10.0) for vx in (9.0, 10.0, 11.0, 0.0, 20.0)]
    print(torques)
    assert torques == [600.0, 0.0, -600.0, 2000.0, -3000.0]


def test_weights_follow_the_speed_schedule() -> None:
    """Low-speed weights at and below the low knot, the others at and above the high one,
    linear in vx between; a flat schedule gives the same weights at every speed."""
    doc = document()
    doc["lmpc"] |= {"q_position": 10.0, "q_yaw": 20.0, "r_steer": 1.0, "low_speed_q_position": 100.0,
                    "low_speed_q_yaw": 80.0, "low_speed_r_steer": 3.0, "weight_schedule_speeds": [10.0, 14.0]}
    table = parse_tuning(doc).lmpc
    assert table.weights_at(0.0) == table.weights_at(10.0) == StageWeights(100.0, 80.0, 3.0)
    assert table.weights_at(14.0) == table.weights_at(40.0) == StageWeights(10.0, 20.0, 1.0)
    assert table.weights_at(11.0) == StageWeights(77.5, 65.0, 2.5)
    flat = with_fixed_weights(table, q_position=3.0)
    assert flat.low_speed_q_position == 3.0 and flat.low_speed_q_yaw == 80.0  # only the twins given
    assert flat.weights_at(5.0).q_position == flat.weights_at(30.0).q_position == 3.0
    explicit = with_fixed_weights(table, q_position=3.0, low_speed_q_position=30.0)
    assert explicit.weights_at(5.0).q_position == 30.0 and explicit.weights_at(30.0).q_position == 3.0
    # The rule on its own (the tuning sweep writes these twins to the tuning file).
    assert low_speed_twins({"q_yaw": 2.0, "q_position": 1.0, "low_speed_q_yaw": 5.0, "p_steer_rate": 0.5}) \
        == {"low_speed_q_position": 1.0}

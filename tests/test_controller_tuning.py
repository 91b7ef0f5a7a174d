"""Tuning file validation and the longitudinal P controller."""
from __future__ import annotations

import tomllib

import pytest

from controller.errors import TuningError
from controller.longitudinal import SpeedController
from controller.tuning import DEFAULT_TUNING_PATH, LongitudinalTuning, load_tuning, parse_tuning


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

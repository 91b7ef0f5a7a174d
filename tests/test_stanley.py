"""The Stanley baseline (controller/stanley.py): the law's signs, its limits, the fallback on
non-finite samples, never raising, its tuning table's validation, and closed-loop
convergence to a straight path from an offset on the real plant. Properties only: no
comparison with the MPCs."""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controller.base import STEER_LIMIT_RAD, Controller, SolverStatus, VehicleSample
from controller.errors import TuningError
from controller.reference import ReferencePath
from controller.registry import (ABLATION_NAMES, ALL_CONTROLLER_NAMES, CONTROLLER_NAMES, GEOMETRIC_NAMES,
                                 MPC_NAMES, create_controller)
from controller.stanley import Stanley, path_curvature, stanley_steer
from controller.tuning import DEFAULT_TUNING_PATH, StanleyTuning, load_tuning, parse_tuning
from hil.scenario import load_scenario
from studies.closed_loop import run_closed_loop

#: Gains for the unit tests (not the tuned ones): no filter, a rate limit that never binds.
PLAIN = StanleyTuning(cross_track_gain=2.0, softening_speed=1.0, yaw_rate_gain=0.0,
                      steer_rate_limit=100.0, steer_time_constant=0.0)


def straight_path(y: float = 0.0) -> ReferencePath:
    x = np.arange(-20.0, 300.0, 0.25)
    return ReferencePath.from_arrays(x, np.full_like(x, y), np.zeros_like(x), name="straight")


def sample(**values: float) -> VehicleSample:
    base = dict(vx=10.0, vy=0.0, yaw_rate=0.0, x=0.0, y=0.0, yaw=0.0, steer_angle=0.0,
                drive_torque=0.0, target_speed=10.0)
    base.update(values)
    return VehicleSample(**base)


def stanley(tuning: StanleyTuning = PLAIN, path: ReferencePath | None = None) -> Stanley:
    controller = Stanley(tuning, load_tuning().longitudinal, front_axle_distance=1.2)
    controller.set_path(path or straight_path())
    return controller


def test_registry_names_keep_the_papers_four_apart() -> None:
    assert GEOMETRIC_NAMES == ("stanley",)
    assert "stanley" in ALL_CONTROLLER_NAMES and "stanley" not in CONTROLLER_NAMES + ABLATION_NAMES
    assert MPC_NAMES == CONTROLLER_NAMES + ABLATION_NAMES
    controller = create_controller("stanley")
    assert isinstance(controller, Stanley) and controller.name == "stanley"
    assert controller.tuning == load_tuning().stanley
    assert controller.front_axle_distance == pytest.approx(1.2)  # nominal lf, models/vehicle.toml


def test_law_signs_and_the_pure_law() -> None:
    # Left of the path or yawed left of it: steer right; the pure law of Hoffmann et al.
    assert stanley_steer(0.0, 0.5, 10.0, 0.0, 0.0, PLAIN) == pytest.approx(-math.atan(2.0 * 0.5 / 11.0))
    assert stanley_steer(0.1, 0.0, 10.0, 0.0, 0.0, PLAIN) == pytest.approx(-0.1)
    assert stanley_steer(-0.1, -0.5, 10.0, 0.0, 0.0, PLAIN) > 0.0
    # Standstill and reversing speeds: the softening speed keeps the gain finite.
    assert stanley_steer(0.0, 0.5, -3.0, 0.0, 0.0, PLAIN) == pytest.approx(-math.atan(1.0))
    # Yaw-rate damping: towards the path's yaw rate vx * kappa.
    damped = replace(PLAIN, yaw_rate_gain=0.5)
    assert stanley_steer(0.0, 0.0, 10.0, 0.0, 0.01, damped) == pytest.approx(0.5 * 0.1)
    assert stanley_steer(0.0, 0.0, 10.0, 0.2, 0.0, damped) == pytest.approx(-0.1)


def test_step_uses_the_front_axle_and_steers_back() -> None:
    controller = stanley()
    # CG on the path, yawed left: the front axle is left of it by lf sin(yaw).
    yaw = 0.05
    command, debug = controller.step(sample(yaw=yaw))
    expected = -yaw - math.atan(2.0 * 1.2 * math.sin(yaw) / 11.0)
    print("steer", command.steer_angle, "expected", expected)
    assert command.steer_angle == pytest.approx(expected, abs=1e-9)
    assert debug.status == SolverStatus.SOLVED and not debug.fallback and debug.iterations == 0
    assert debug.predicted_pose.shape == (0, 3)
    assert command.drive_torque == pytest.approx(0.0)  # at the target speed


def test_curvature_of_a_circle() -> None:
    radius = 50.0
    angle = np.arange(0.0, 1.5, 0.25 / radius)
    path = ReferencePath.from_arrays(radius * np.sin(angle), radius * (1.0 - np.cos(angle)), angle)
    curvature = path_curvature(path)
    print("curvature range", curvature.min(), curvature.max())
    np.testing.assert_allclose(curvature, 1.0 / radius, rtol=1e-3)


@pytest.mark.parametrize("offset", [-50.0, -3.0, 3.0, 50.0])
def test_commands_stay_within_the_steering_limit(offset: float) -> None:
    controller = stanley(replace(PLAIN, cross_track_gain=100.0, yaw_rate_gain=5.0))
    for _ in range(5):
        command, _ = controller.step(sample(y=offset, yaw_rate=-offset, yaw=0.3 * np.sign(offset)))
        assert abs(command.steer_angle) <= STEER_LIMIT_RAD
    assert abs(command.steer_angle) == STEER_LIMIT_RAD


def test_rate_limit_and_low_pass() -> None:
    limited = stanley(replace(PLAIN, steer_rate_limit=1.0))
    steps = [limited.step(sample(y=2.0))[0].steer_angle for _ in range(4)]
    print("rate-limited steer", steps)
    np.testing.assert_allclose(np.diff([0.0] + steps), -0.025, atol=1e-12)  # 1 rad/s at 25 ms
    filtered = stanley(replace(PLAIN, steer_time_constant=0.075))
    raw = stanley().step(sample(y=0.2))[0].steer_angle
    first = filtered.step(sample(y=0.2))[0].steer_angle
    assert first == pytest.approx(raw * 0.025 / (0.075 + 0.025))
    # The filter starts from the measured wheel angle on the first step after a reset.
    filtered.reset()
    assert filtered.step(sample(y=0.0, steer_angle=0.1))[0].steer_angle == pytest.approx(0.1 * 0.75)


@pytest.mark.parametrize("field", ["vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque",
                                   "target_speed"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_sample_holds_the_previous_command(field: str, bad: float) -> None:
    controller = stanley()
    good, _ = controller.step(sample(y=0.3, target_speed=12.0))
    command, debug = controller.step(sample(**{field: bad}))
    assert debug.status == SolverStatus.NOT_RUN and debug.fallback
    assert command == good
    # Before any command: zero steer and torque.
    fresh = stanley()
    command, debug = fresh.step(sample(**{field: bad}))
    assert (command.steer_angle, command.drive_torque) == (0.0, 0.0) and debug.fallback


def test_no_path_and_absurd_samples_never_raise() -> None:
    controller = Stanley(PLAIN, load_tuning().longitudinal, front_axle_distance=1.2)
    command, debug = controller.step(sample())
    assert debug.status == SolverStatus.NOT_RUN and command.steer_angle == 0.0
    controller.set_path(straight_path())
    rng = np.random.default_rng(35)
    for values in rng.normal(scale=[30, 5, 2, 1e3, 1e3, 10, 1, 1e4, 30], size=(300, 9)):
        command, _ = controller.step(VehicleSample(*values))
        assert math.isfinite(command.steer_angle) and abs(command.steer_angle) <= STEER_LIMIT_RAD
        assert math.isfinite(command.drive_torque)
    command, debug = controller.step(sample(x=1e308, y=1e308, yaw=0.7))
    print("near-overflow position:", command, debug.status.name)
    assert math.isfinite(command.steer_angle) and abs(command.steer_angle) <= STEER_LIMIT_RAD


def test_closed_loop_converges_to_a_straight_path_from_an_offset() -> None:
    """The real plant at 35 km/h, starting 1 m left of a straight path, shipped tuning."""
    scenario = load_scenario("dlc_smoke")
    scenario = replace(scenario, duration_s=4.0,
                       start=replace(scenario.start, x_m=0.0, y_m=1.0, yaw_rad=0.0))
    result = run_closed_loop(scenario, create_controller("stanley"), reference_path=straight_path())
    error = result.trace.lateral_error
    late = np.abs(error[result.trace.time_s >= 3.0])
    print(f"e_Y start {error[0]:.3f} m, min {error.min():.3f} m, |e_Y| after 3 s <= {late.max():.4f} m, "
          f"steer within limit: {result.steer_limit_held}")
    assert result.completed and result.steer_limit_held
    assert error[0] == pytest.approx(1.0, abs=0.05)
    assert late.max() < 0.05
    # The tuned gains are stiff (the steer saturates at the start): some overshoot, bounded.
    assert error.min() > -0.5


def test_tuning_table_errors_name_field_and_value() -> None:
    with DEFAULT_TUNING_PATH.open("rb") as handle:
        document = tomllib.load(handle)
    for field, value, message in (
            ("cross_track_gain", 0.0, "[stanley] cross_track_gain must be > 0, got 0.0"),
            ("softening_speed", -1.0, "[stanley] softening_speed must be > 0, got -1.0"),
            ("yaw_rate_gain", -0.1, "[stanley] yaw_rate_gain must be >= 0, got -0.1"),
            ("steer_rate_limit", 0.0, "[stanley] steer_rate_limit must be > 0, got 0.0"),
            ("steer_time_constant", "slow", "[stanley] steer_time_constant must be a finite number, got 'slow'")):
        bad = {**document, "stanley": {**document["stanley"], field: value}}
        with pytest.raises(TuningError) as error:
            parse_tuning(bad)
        print(error.value)
        assert message in str(error.value)
    missing = {**document, "stanley": {k: v for k, v in document["stanley"].items() if k != "yaw_rate_gain"}}
    with pytest.raises(TuningError, match=r"\[stanley\] missing field\(s\) \['yaw_rate_gain'\]"):
        parse_tuning(missing)
    with pytest.raises(TuningError, match="front_axle_distance must be a finite number > 0 m, got 0.0"):
        Stanley(PLAIN, load_tuning().longitudinal, front_axle_distance=0.0)
    assert [f.name for f in dataclasses.fields(StanleyTuning)] == list(document["stanley"])


def test_takes_no_model_file(tmp_path) -> None:
    from controller.registry import ModelFileError

    with pytest.raises(ModelFileError, match="controller 'stanley' takes no model file"):
        create_controller("stanley", model_path=tmp_path / "model.npz")


def test_is_a_controller() -> None:
    assert issubclass(Stanley, Controller)


def test_hil_run_over_can_and_the_ecu_command_line(tmp_path, capsys) -> None:
    """``eso-hil run --controller stanley`` drives the Python ECU over the virtual bus in
    lockstep; the ECU's command line accepts it and refuses the C core (which has none)."""
    import json

    from firmware_sim import cli
    from hil.__main__ import main as hil_main

    out = tmp_path / "run"
    out.mkdir()
    assert hil_main(["run", "--controller", "Stanley", "--scenario", "dlc_smoke", "--out", str(out),
                     "--log", str(out / "dlc_smoke__stanley.log")]) == 0
    summary = json.loads((out / "summary.json").read_text())
    print({k: summary[k] for k in ("controller", "control_cycles", "active_cycles")},
          summary["tracking"]["lateral_error_m"])
    assert summary["controller"] == "stanley"
    assert summary["active_cycles"] == summary["control_cycles"] - 1
    assert summary["tracking"]["lateral_error_m"]["max_abs"] < 0.1
    assert "stanley" in cli.CONTROLLER_CHOICES
    dlc = Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"
    status = cli.main(["--controller", "stanley", "--native", "--path", f"1={dlc}", "--lockstep",
                       "--interface", "virtual", "--channel", "stanley-test"])
    assert status == 2 and "not in the C core" in capsys.readouterr().err


def test_campaign_leaves_the_c_ecu_cells_out(tmp_path) -> None:
    """A campaign grid may name stanley; its C ECU cells are left out with the reason, as
    NMPC's are."""
    from studies.campaign.grid import load_grid

    file = tmp_path / "grid.toml"
    file.write_text('[axes]\ncontroller = ["stanley", "lmpc"]\nscenario = ["dlc_smoke"]\necu = ["python", "c"]\n')
    grid = load_grid(file)
    print(sorted((c.controller, c.ecu) for c in grid.cells), grid.c_left_out)
    assert sorted((c.controller, c.ecu) for c in grid.cells) == [("lmpc", "c"), ("lmpc", "python"),
                                                                 ("stanley", "python")]
    assert grid.c_left_out == {"the C ECU has no stanley (Python only)": 1}

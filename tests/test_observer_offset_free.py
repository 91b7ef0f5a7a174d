"""The observer as an offset-free disturbance model (shared/spec/offset-free.md): the
innovation bound, the yaw-rate bias estimate, detectability of the shipped model, tracking
without a standing offset under a constant disturbance, and the C core's twin of it all."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from controller.eso_dkmpc import LATERAL_ROWS
from models.eso import PERSISTENCE_MAX_FACTOR, EsoShapeError, InnovationSaturation, PersistentInnovationBound
from models.koopman import KoopmanModel
from models.yaw_rate_bias import YawRateBiasState, yaw_rate_bias_update
from c_twin import Twin, assert_twin_steps_equal
from test_firmware_c_core import native  # noqa: F401 (the fixture: libecu.so built and loaded)
from tuning_helpers import controller_with

TS = 0.025


def test_innovation_bound_is_the_identity_below_the_limit_and_scales_above() -> None:
    bound = InnovationSaturation((1, 2), 0.003)
    small = np.array([0.5, 0.002, -0.001, 0.3])
    assert np.array_equal(bound(small), small)
    large = np.array([0.5, 0.012, -0.003, 0.3])
    bounded = bound(large)
    assert np.max(np.abs(bounded[[1, 2]])) == pytest.approx(0.003)
    assert np.allclose(bounded, large / 4.0)  # the direction is kept
    assert np.array_equal(InnovationSaturation((1, 2), 0.0)(large), large)  # 0: no bound
    assert np.isnan(bound(np.array([0.0, math.nan, 0.0, 0.0]))[1])
    with pytest.raises(EsoShapeError, match="innovation limit"):
        InnovationSaturation((1, 2), -1.0)


def test_persistent_bound_widens_while_the_innovation_keeps_its_sign_beyond_it() -> None:
    bound = PersistentInnovationBound((1, 2), 0.003, 10.0)
    beyond = np.array([0.5, 0.012, -0.003, 0.3])  # the vy entry leads: sign +
    for n in range(1, 6):
        assert bound.limit == pytest.approx(0.003 * (1.0 + (n - 1) / 10.0))
        assert np.max(np.abs(bound(beyond)[[1, 2]])) == pytest.approx(bound.limit)
        bound.advance(beyond)
        assert bound.saturated_steps == n
    bound.advance(-beyond)  # a sign change starts a new count
    assert bound.saturated_steps == 1 and bound.sign == -1.0
    bound.advance(np.array([0.5, 0.001, 0.002, 0.3]))  # within the bound: back to the limit
    assert bound.saturated_steps == 0 and bound.limit == 0.003
    for _ in range(1000):  # never wider than PERSISTENCE_MAX_FACTOR x the limit
        bound.advance(beyond * 100.0)
    assert bound.limit == pytest.approx(0.003 * PERSISTENCE_MAX_FACTOR)
    bound.advance(np.array([0.0, math.nan, 0.0, 0.0]))  # non-finite: back to the limit
    assert bound.limit == 0.003
    bound.advance(beyond)
    bound.restart()
    assert bound.saturated_steps == 0 and bound.limit == 0.003


def test_persistent_bound_with_zero_persistence_is_the_fixed_bound() -> None:
    fixed, persistent = InnovationSaturation((1, 2), 0.003), PersistentInnovationBound((1, 2), 0.003, 0.0)
    beyond = np.array([0.5, 0.012, -0.003, 0.3])
    for _ in range(5):
        persistent.advance(beyond)
        assert np.array_equal(persistent(beyond), fixed(beyond)) and persistent.limit == 0.003
    unbounded = PersistentInnovationBound((1, 2), 0.0, 10.0)
    unbounded.advance(beyond)
    assert np.array_equal(unbounded(beyond), beyond) and unbounded.saturated_steps == 0
    with pytest.raises(EsoShapeError, match="persistence"):
        PersistentInnovationBound((1, 2), 0.003, -1.0)


def test_persistent_bound_widens_only_below_the_lateral_acceleration_gate() -> None:
    """With a gate, a step at or beyond it (a manoeuvre, or a non-finite value) restarts the
    count; below it the bound widens as without a gate. Gate 0: every step counts."""
    beyond = np.array([0.5, 0.012, -0.003, 0.3])
    gated, ungated = PersistentInnovationBound((1, 2), 0.003, 10.0, 0.5), PersistentInnovationBound((1, 2), 0.003, 10.0)
    for n in range(1, 4):
        gated.advance(beyond, 0.49)
        ungated.advance(beyond, 5.0)
        assert gated.saturated_steps == ungated.saturated_steps == n
    assert gated.limit == ungated.limit > 0.003
    gated.advance(beyond, -0.5)  # |a_y| at the gate: a manoeuvre
    assert gated.saturated_steps == 0 and gated.limit == 0.003
    gated.advance(beyond, 0.1)
    gated.advance(beyond, math.nan)
    assert gated.saturated_steps == 0
    with pytest.raises(EsoShapeError, match="lateral acceleration gate"):
        PersistentInnovationBound((1, 2), 0.003, 10.0, -0.1)
    with pytest.raises(EsoShapeError, match="lateral acceleration gate"):
        PersistentInnovationBound((1, 2), 0.003, 10.0, math.inf)


def _turning_samples(bias: float, n: int, yaw_rate: float = 0.2) -> list[tuple[float, float]]:
    """(heading, measured yaw rate) of a car turning at ``yaw_rate`` (rad/s), sampled at 20
    and 30 ms alternately (the ECU's sample ages), the rate reading ``bias`` high and the
    heading quantised to VEH_POSE_YAW's 1e-4 rad and wrapped."""
    samples, t = [], 0.0
    for k in range(n):
        t += 0.020 if k % 2 else 0.030
        heading = math.remainder(round(yaw_rate * t / 1e-4) * 1e-4, 2.0 * math.pi)
        samples.append((heading, yaw_rate + bias))
    return samples


def test_yaw_rate_bias_is_found_from_the_heading_through_the_wrap() -> None:
    state = YawRateBiasState()
    for heading, rate in _turning_samples(0.01, 2000):  # 50 s: the heading wraps 3 times
        state = yaw_rate_bias_update(state, heading, rate, 0.99, TS)
    print(f"bias estimate {state.bias:.5f} rad/s for 0.01")
    assert state.bias == pytest.approx(0.01, abs=5e-4)


def test_yaw_rate_bias_pole_one_keeps_zero_and_a_gap_skips_an_update() -> None:
    state = YawRateBiasState()
    for heading, rate in _turning_samples(0.01, 200):
        state = yaw_rate_bias_update(state, heading, rate, 1.0, TS)
    assert state.bias == 0.0
    state = YawRateBiasState(0.004, 0.1, 0.2)
    gap = yaw_rate_bias_update(state, math.nan, 0.2, 0.99, TS)
    assert gap.bias == 0.004 and gap.previous_yaw is None
    restart = yaw_rate_bias_update(gap, 1.0, 0.2, 0.99, TS)  # far away: not compared with 0.1
    assert restart.bias == 0.004 and restart.previous_yaw == 1.0


def test_lifted_disturbance_model_is_detectable_at_every_speed_knot() -> None:
    """Rank condition of Pannocchia and Rawlings: rank [[A - I, Bd], [C, Cd]] = n + nd.

    The observer measures the whole lifted state z = lift(x) (C = I, ny = n_z) and places w
    on every lifted row (Bd = I, Cd = 0, nd = n_z): detectable for any A. Measuring only the
    four physical states (C = C_P) would leave n_z - 4 directions of w undetectable; the
    observer reaches them through the lift, which it takes as exact."""
    model = KoopmanModel.load()
    n_z = model.n_z
    for knot in model.speed_knots:
        A = model.at_speed(float(knot)).A
        lifted = np.block([[A - np.eye(n_z), np.eye(n_z)], [np.eye(n_z), np.zeros((n_z, n_z))]])
        assert np.linalg.matrix_rank(lifted) == 2 * n_z, f"not detectable at {knot} m/s"
        physical = np.block([[A - np.eye(n_z), np.eye(n_z)], [model.C_P, np.zeros((model.C_P.shape[0], n_z))]])
        assert np.linalg.matrix_rank(physical) < 2 * n_z
    assert LATERAL_ROWS == (1, 2)


def _straight_scenario(folder: Path, disturbances: str) -> "object":
    """A 20 s straight at 50 km/h on mu 0.85 with the given ``[disturbances]`` body."""
    from hil.scenario import load_scenario

    xs = np.arange(-20.0, 420.0, 0.25)
    (folder / "straight.csv").write_text("x,y,yaw\n" + "".join(f"{x:.6f},0.000000,0.000000\n" for x in xs))
    (folder / "straight.toml").write_text(f"""name = "straight_disturbed"
duration_s = 20.0
[path]
id = 9
file = "straight.csv"
[road]
mu = 0.85
[start]
x_m = 0.0
y_m = 0.0
yaw_rad = 0.0
speed_kmh = 50.0
[speed_profile]
time_s = [0.0]
target_speed_kmh = [50.0]
[disturbances]
{disturbances}
""")
    return load_scenario(folder / "straight.toml")


@pytest.mark.slow
@pytest.mark.parametrize("disturbance, observer", [
    ("steer_offset_rad = 0.02", {}),  # the shipped tuning
    ("steer_offset_rad = 0.02", {"eso_innovation_persistence": 10.0}),  # the bound widening
    ("steer_offset_rad = 0.02", {"eso_innovation_persistence": 10.0, "eso_widening_lateral_accel": 0.5}),  # gated
    ("yaw_rate_bias_rad_s = 0.01", {}),  # the shipped tuning: the bias estimate on
    ("yaw_rate_bias_rad_s = 0.01", {"yaw_rate_bias_pole": 0.99}),  # a slower estimate
    # the car must crab: with the heading target moved by the steady side slip
    ("crosswind_force_n = 800.0\ncrosswind_cp_m = 0.6", {"slip_target_limit": 0.02, "slip_target_gate": 0.003}),
    ("bank_angle_rad = 0.06", {"slip_target_limit": 0.02, "slip_target_gate": 0.003}),
])
def test_eso_dkmpc_settles_without_a_standing_offset(tmp_path: Path, disturbance: str,
                                                     observer: dict[str, float]) -> None:
    """A constant disturbance on a straight road: after 12 s the lateral error of ESO-DKMPC
    stays within 5 mm (the wheels' offset alone moves the car 0.02 rad x 13.9 m/s = 0.28 m/s
    sideways before the controller acts). The sensor bias needs the bias estimate, which the
    shipped tuning has on (results/observer_tuning_refine.md)."""
    from studies.closed_loop import run_closed_loop

    scenario = _straight_scenario(tmp_path, disturbance)
    result = run_closed_loop(scenario, controller_with("eso-dkmpc", **observer))
    assert result.completed, result.failure
    trace = result.trace
    settled = np.abs(trace.lateral_error[trace.time_s >= 12.0])
    print(f"{disturbance}: |e_Y| after 12 s at most {settled.max() * 1000:.2f} mm")
    assert settled.max() < 0.005


def _c_core_with(native, folder: Path, controller: str = "eso-dkmpc", **observer: float) -> "object":
    """The C core's ``controller`` on the build's data file with the given fields of its
    tuning table replaced, as ``controller_with(controller, **observer)`` replaces them in Python."""
    from test_firmware_c_core import _tool

    ecu_data = _tool("ecu_data")
    records = ecu_data.collect(None, ecu_data.DEFAULT_ARTIFACT)
    table = records[f"tuning.{controller}"].copy()
    fields = list(ecu_data.TUNING_FIELDS)
    for name, value in observer.items():
        table[len(table) - len(fields) + fields.index(name)] = value  # after the 3-vector bounds
    path = folder / f"{controller}-{'-'.join(observer) or 'tuning'}.bin"
    ecu_data.write_data(dict(records, **{f"tuning.{controller}": table}), path)
    return native.NativeController(controller, path)


@pytest.mark.parametrize("persistence, gate", [(0.0, 0.0), (10.0, 0.0), (10.0, 0.2)])
def test_c_core_observer_equals_python_under_a_yaw_rate_bias_and_a_steering_offset(native, tmp_path: Path,
                                                                                    persistence: float,
                                                                                    gate: float) -> None:
    """The yaw-rate bias estimate and the innovation bound in the C core: under a sensor bias
    and a steering offset on a straight (both act, the bound is reached in the first steps),
    the same commands, status and iterations as the Python ESO-DKMPC step for step, with
    the fixed bound, with the bound widening (eso_innovation_persistence) and with the
    widening gated on the lateral acceleration (eso_widening_lateral_accel, crossed in the
    first second)."""
    from studies.closed_loop import run_closed_loop

    scenario = dataclasses.replace(_straight_scenario(tmp_path, "steer_offset_rad = 0.02\nyaw_rate_bias_rad_s = 0.01"),
                                   duration_s=6.0)
    # The bias estimate on in both (as the shipped tuning has it) and the bound reached.
    fields = {"yaw_rate_bias_pole": 0.99, "eso_innovation_persistence": persistence,
              "eso_widening_lateral_accel": gate}
    python = controller_with("eso-dkmpc", **fields)
    twin = Twin(python, _c_core_with(native, tmp_path, **fields), frozenset({60, 61}))
    widest, gated = 0, 0
    original_advance = python.innovation_bound((1, 2)).advance

    def advance(z_tilde: np.ndarray, lateral_accel: float) -> None:
        nonlocal widest, gated
        original_advance(z_tilde, lateral_accel)
        widest = max(widest, python.innovation_bound((1, 2)).saturated_steps)
        gated += gate > 0.0 and abs(lateral_accel) >= gate

    python.innovation_bound((1, 2)).advance = advance
    result = run_closed_loop(scenario, twin)
    assert result.completed, result.failure
    assert_twin_steps_equal("eso-dkmpc", twin)
    assert abs(python.yaw_rate_bias) > 0.005  # the estimate moved: the corrected path ran
    print(f"persistence {persistence}, gate {gate}: the bound widened over at most {widest} steps, "
          f"{gated} steps at or beyond the gate")
    assert (widest >= 10) == (persistence > 0.0)  # the widening ran where it is on
    assert (gated > 0) == (gate > 0.0)  # and the gate closed where there is one


@pytest.mark.parametrize("controller", ["eso-dkmpc", "dkmpc", "lmpc"])
def test_c_core_equals_python_with_the_slip_target_under_a_crosswind(native, tmp_path: Path, controller: str) -> None:
    """The heading target's measured side slip in the C core (ecu_steady_slip.c), for each
    of its MPCs: under an 800 N crosswind on a straight, with the target on in both (the
    shipped tuning leaves it off), the same commands, status, iterations and predictions as
    the Python controller step for step; two invalid samples restart the observer."""
    from studies.closed_loop import run_closed_loop

    scenario = dataclasses.replace(_straight_scenario(tmp_path, "crosswind_force_n = 800.0\ncrosswind_cp_m = 0.6"),
                                   duration_s=6.0)
    observer = {"slip_target_limit": 0.02, "slip_target_gate": 0.003}
    python = controller_with(controller, **observer)
    twin = Twin(python, _c_core_with(native, tmp_path, controller, **observer), frozenset({60, 61}))
    result = run_closed_loop(scenario, twin)
    assert result.completed, result.failure
    assert_twin_steps_equal(controller, twin)
    print(f"slip target at the end {python.slip_target:.5f} rad")
    assert abs(python.slip_target) > 1e-4  # the target moved: the shifted reference ran


@pytest.mark.parametrize("controller, field, value", [
    ("eso-dkmpc", "slip_target_limit", 0.25), ("eso-dkmpc", "slip_target_limit", -0.01),
    ("dkmpc", "slip_target_gate", 0.0), ("lmpc", "slip_target_gate", 1.5)])
def test_c_core_refuses_the_slip_target_fields_python_refuses(native, tmp_path: Path, controller: str, field: str,
                                                              value: float) -> None:
    """Out of its range, a heading target field is refused by both loaders with one message
    naming it (controller.tuning's rule); the ends of the ranges load in both."""
    import tomllib

    from controller.errors import TuningError
    from controller.tuning import DEFAULT_TUNING_PATH, parse_tuning
    from firmware_sim.errors import ConfigError

    document = tomllib.loads(Path(DEFAULT_TUNING_PATH).read_text())
    document[controller][field] = value
    with pytest.raises(TuningError) as python_error:
        parse_tuning(document)
    with pytest.raises(ConfigError) as c_error:
        _c_core_with(native, tmp_path, controller, **{field: value})
    print(c_error.value)
    assert str(python_error.value) in str(c_error.value)
    assert f"] {field} must be in" in str(python_error.value)
    document[controller].update(slip_target_limit=0.2, slip_target_gate=1.0)
    parse_tuning(document)
    _c_core_with(native, tmp_path, controller, slip_target_limit=0.2, slip_target_gate=1.0)


@pytest.mark.parametrize("field, value, ends", [
    *(("eso_innovation_persistence", value, (0.0, 1000.0)) for value in (-1.0, 1000.5, math.nan)),
    *(("eso_widening_lateral_accel", value, (0.0, 20.0)) for value in (-0.1, 20.5, math.nan))])
def test_both_loaders_refuse_a_widening_field_out_of_range(native, tmp_path: Path, field: str, value: float,
                                                           ends: tuple[float, float]) -> None:
    """The bound's widening (eso_innovation_persistence, steps) and its gate
    (eso_widening_lateral_accel, m/s^2) outside their ranges: refused by the Python loader
    and by the C core's, each naming the field; the ends of the range load in both."""
    import tomllib

    from controller.errors import TuningError
    from controller.tuning import DEFAULT_TUNING_PATH, parse_tuning
    from firmware_sim.errors import ConfigError

    document = tomllib.loads(Path(DEFAULT_TUNING_PATH).read_text())
    document["eso-dkmpc"][field] = value
    with pytest.raises(TuningError, match=rf"\[eso-dkmpc\] {field} must be "):
        parse_tuning(document)
    low, high = ends
    with pytest.raises(ConfigError, match=rf"{field} in \[{low:g}, {high:g}\]"):
        _c_core_with(native, tmp_path, **{field: value})
    for end in ends:
        document["eso-dkmpc"][field] = end
        assert getattr(parse_tuning(document).eso_dkmpc, field) == end
        _c_core_with(native, tmp_path, **{field: end})

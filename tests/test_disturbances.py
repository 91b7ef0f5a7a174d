"""Disturbances on the plant alone (models/disturbance.py, docs/plant.md "Disturbances"):
open-loop drives at 50 km/h with zero steer, each disturbance against the linear bicycle's
steady state with the same external force and moment; the sensor bias on the reported
signal only; start_s and the gust's window; bad [disturbances] tables refused; the HIL
plant node and the closed-loop runner build the same disturbed plant."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from hil.errors import ScenarioError
from hil.fault_injector import FaultInjector
from hil.fault_vehicle import OffsetSteeringVehicle
from hil.faults import FaultSpec
from hil.path_files import DLC_PATH_FILE
from hil.plant_node import PlantNode
from hil.scenario import Scenario
from models.bicycle import LinearBicycle, NominalModelParams, nominal_model_params
from models.disturbance import DisturbanceError, Disturbances, DisturbanceSchedule
from models.vehicle import N_STATE, FourWheelVehicle, PlantModel, ScalarPlant, VehicleCommand
from models.vehicle_params import VehicleParams, load_vehicle_params
from studies.closed_loop import default_plant

SPEED = 50.0 / 3.6
TICK_S = 0.005
#: Open-loop drive length (s): the lateral and yaw modes (time constants ~0.1-0.2 s) settle.
SETTLE_S = 4.0


def _hold_speed_torque(params: VehicleParams, vx: float) -> float:
    """Drive torque (N m) that balances drag and rolling resistance at ``vx``, with a
    proportional term that holds the speed (wheels' spin and slip are left to the plant)."""
    resistance = (0.5 * params.air_density * params.drag_coefficient * params.frontal_area * vx * vx
                  + params.rolling_resistance * params.mass * params.gravity)
    return resistance * params.radius + 4000.0 * (SPEED - vx)


def _drive(disturbances: Disturbances | None, steer: float = 0.0, seconds: float = SETTLE_S,
           params: VehicleParams | None = None) -> tuple[FourWheelVehicle, np.ndarray]:
    """Open loop at 50 km/h with a constant steering command; returns the vehicle and the
    trace, rows (time, vx, vy, true yaw rate, x, y, reported yaw rate, reported steer, true
    steer), shape (n, 9)."""
    params = params or load_vehicle_params()
    vehicle = FourWheelVehicle(params, disturbances=disturbances)
    vehicle.reset(vx=SPEED)
    rows = []
    for _ in range(int(round(seconds / TICK_S))):
        true, reported = vehicle.true_outputs(), vehicle.outputs()
        rows.append((vehicle.time_s, true.vx, true.vy, true.yaw_rate, true.x, true.y,
                     reported.yaw_rate, reported.steer_angle, true.steer_angle))
        vehicle.step(VehicleCommand(_hold_speed_torque(params, true.vx), steer), TICK_S)
    return vehicle, np.array(rows)


def _linear_steady_state(nominal: NominalModelParams, vx: float, steer: float, force_y: float,
                         yaw_moment: float) -> tuple[float, float]:
    """(vy, yaw rate) of the linear bicycle in steady state with the front wheel angle
    ``steer`` (rad), an external lateral force at the CG (N) and a yaw moment (N m)."""
    a, b = LinearBicycle(nominal).continuous_matrices(vx)
    external = np.array([force_y / nominal.mass, yaw_moment / nominal.yaw_inertia])
    vy, yaw_rate = -np.linalg.solve(a, b[:, 0] * steer + external)
    return float(vy), float(yaw_rate)


# ---------------------------------------------------------------------------- nominal

def test_no_disturbance_is_bit_identical_to_the_plant_without_them():
    """Disturbances() and disturbances that start after the drive change nothing, to the
    bit (the nominal plant's own equality to the code before them was checked against
    the previous commit when they were added)."""
    _, plain = _drive(None, steer=0.01, seconds=1.0)
    _, empty = _drive(Disturbances(), steer=0.01, seconds=1.0)
    _, later = _drive(Disturbances(start_s=5.0, crosswind_force_n=800.0, steer_offset_rad=0.02,
                                   yaw_rate_bias_rad_s=0.01, pull_wheel="FL", pull_stiffness_scale=0.5),
                      steer=0.01, seconds=1.0)
    assert np.array_equal(plain, empty) and np.array_equal(plain, later)


@pytest.mark.parametrize("disturbance", [
    Disturbances(steer_offset_rad=0.02, bank_angle_rad=-0.05, crosswind_force_n=600.0, crosswind_cp_m=0.5,
                 pull_wheel="RL", pull_stiffness_scale=0.6),
    Disturbances(gust_force_n=-900.0, gust_duration_s=1.0, pull_wheel="FR", pull_stiffness_scale=1.4),
])
def test_scalar_derivative_equals_vectorised_with_a_disturbance(disturbance):
    params = dataclasses.replace(load_vehicle_params(), cornering_stiffness_rear_scale=0.8)
    model = PlantModel(params)
    scalar = ScalarPlant(model)
    inputs = DisturbanceSchedule(disturbance, params).at(0.5)
    rng = np.random.default_rng(1)
    states = model.initial_state(rng.uniform(0.0, 40.0, 100))
    states += rng.normal(0.0, 1.0, states.shape) * np.array(
        [1, 0.5, 0.3, 10, 10, 3, 5, 5, 5, 5, 0.05, 0.05, 0.05, 0.05, 0.1, 1000, 3, 3])
    steer, torque, mu = rng.uniform(-0.4, 0.4, 100), rng.uniform(-4000, 4000, 100), rng.uniform(0.3, 1.0, 100)
    batch = model.derivatives(states, steer, torque, mu, inputs)
    nominal = model.derivatives(states, steer, torque, mu)
    single = np.array([scalar.derivatives(states[i].tolist(), steer[i], torque[i], mu[i], inputs)
                       for i in range(100)])
    worst = float(np.max(np.abs(single - batch) / (1.0 + np.abs(batch))))
    print(f"{disturbance.describe()}: scalar vs vectorised max relative difference {worst:.2e}")
    assert worst < 1e-9 and single.shape == (100, N_STATE)
    assert not np.allclose(batch, nominal)  # the disturbance reached the derivative


# ---------------------------------------------------------------------------- each kind

@pytest.mark.parametrize("name, disturbance, force_y, yaw_moment, steer", [
    ("steering offset", Disturbances(steer_offset_rad=0.01), 0.0, 0.0, 0.01),
    ("bank 3 %", Disturbances(bank_angle_rad=math.atan(0.03)), "bank", 0.0, 0.0),
    ("crosswind 400 N", Disturbances(crosswind_force_n=400.0, crosswind_cp_m=0.6), 400.0, 240.0, 0.0),
])
def test_constant_disturbance_drifts_left_at_the_linear_bicycles_rate(name, disturbance, force_y, yaw_moment, steer):
    params = load_vehicle_params()
    if force_y == "bank":
        force_y = params.mass * params.gravity * math.sin(disturbance.bank_angle_rad)
    _, trace = _drive(disturbance)
    vy, yaw_rate = trace[-1, 2], trace[-1, 3]
    expected_vy, expected_r = _linear_steady_state(nominal_model_params(params), trace[-1, 1], steer,
                                                   force_y, yaw_moment)
    print(f"{name}: after {SETTLE_S:g} s vy {vy:+.5f} m/s (linear {expected_vy:+.5f}), yaw rate "
          f"{yaw_rate:+.5f} rad/s (linear {expected_r:+.5f}), y {trace[-1, 5]:+.3f} m")
    assert trace[-1, 5] > 0.05 and yaw_rate > 0.0          # drifts and turns to the left
    assert yaw_rate == pytest.approx(expected_r, rel=0.03)
    assert vy == pytest.approx(expected_vy, rel=0.03)
    # The mirror image drifts to the right by as much.
    mirrored = dataclasses.replace(disturbance, steer_offset_rad=-disturbance.steer_offset_rad,
                                   bank_angle_rad=-disturbance.bank_angle_rad,
                                   crosswind_force_n=-disturbance.crosswind_force_n)
    _, mirror = _drive(mirrored)
    assert mirror[-1, 5] == pytest.approx(-trace[-1, 5], rel=1e-6)


@pytest.mark.parametrize("disturbance", [Disturbances(bank_angle_rad=math.atan(0.06)),
                                         Disturbances(crosswind_force_n=-800.0, crosswind_cp_m=0.6)])
def test_at_zero_slip_the_accelerations_are_the_external_loads_alone(disturbance):
    """Straight rolling, tyres at zero slip: the lateral acceleration is g sin(phi) + F / m
    and the yaw acceleration F x_cp / Iz, exactly."""
    params = load_vehicle_params()
    model = PlantModel(params)
    state = model.initial_state(np.array([SPEED]))
    nominal = model.derivatives(state, np.zeros(1), np.zeros(1), np.array([params.mu]))
    disturbed = model.derivatives(state, np.zeros(1), np.zeros(1), np.array([params.mu]),
                                  DisturbanceSchedule(disturbance, params).at(0.0))
    force = disturbance.crosswind_force_n
    lateral = params.gravity * math.sin(disturbance.bank_angle_rad) + force / params.mass
    print(f"{disturbance.describe()}: dvy/dt {disturbed[0, 1]:+.5f} m/s^2 (expected {lateral:+.5f}), "
          f"dr/dt {disturbed[0, 2]:+.5f} rad/s^2")
    assert disturbed[0, 1] - nominal[0, 1] == pytest.approx(lateral, rel=1e-9)
    assert disturbed[0, 2] - nominal[0, 2] == pytest.approx(force * disturbance.crosswind_cp_m
                                                            / params.yaw_inertia, rel=1e-9, abs=1e-12)


def test_steering_offset_is_seen_neither_in_the_command_nor_in_steer_angle():
    _, trace = _drive(Disturbances(steer_offset_rad=0.02), seconds=1.0)
    assert np.all(trace[:, 7] == 0.0)                  # STEER_ANGLE: the actuator's state, 0
    np.testing.assert_allclose(trace[:, 8], 0.02)       # the true wheel angle
    # Same car motion as a straight-driving car steered to 0.02 rad by its actuator,
    # except for the actuator's lag at the start.
    _, steered = _drive(None, steer=0.02, seconds=SETTLE_S)
    _, offset = _drive(Disturbances(steer_offset_rad=0.02), seconds=SETTLE_S)
    assert offset[-1, 3] == pytest.approx(steered[-1, 3], rel=1e-3)


def test_the_fault_offset_shows_in_steer_angle_the_disturbance_does_not():
    """hil/faults.py's [faults.vehicle] steer_offset_rad: the actuator settles at command +
    offset, so STEER_ANGLE reports it (unchanged by the disturbances)."""
    fault = OffsetSteeringVehicle(load_vehicle_params(), 0.02)
    fault.reset(vx=SPEED)
    for _ in range(200):
        fault.step(VehicleCommand(0.0, 0.0), TICK_S)
    assert fault.outputs().steer_angle == pytest.approx(0.02, rel=1e-6)


def test_yaw_rate_bias_is_on_the_reported_signal_only():
    _, plain = _drive(None, steer=0.01, seconds=2.0)
    _, biased = _drive(Disturbances(yaw_rate_bias_rad_s=0.01), steer=0.01, seconds=2.0)
    assert np.array_equal(plain[:, :6], biased[:, :6])                 # the motion: bit for bit
    np.testing.assert_allclose(biased[:, 6] - biased[:, 3], 0.01, atol=1e-12)


def test_pulling_tyre_changes_the_yaw_gain_not_the_straight():
    """One tyre's cornering stiffness x 0.5: no force at zero slip, so no drift on a
    straight; in steady turns the front axle is softer (about (1 + 0.5) / 2 of its
    stiffness): more understeer, a little more in right turns, where FR is the outer,
    loaded tyre."""
    pull = Disturbances(pull_wheel="FR", pull_stiffness_scale=0.5)
    _, straight = _drive(pull)
    assert abs(straight[-1, 5]) < 1e-9 and abs(straight[-1, 3]) < 1e-12
    params = load_vehicle_params()
    nominal = nominal_model_params(params)
    softer = dataclasses.replace(nominal, cornering_stiffness_front=0.75 * nominal.cornering_stiffness_front)
    ratio_linear = (LinearBicycle(softer).steady_state_yaw_rate_gain(SPEED)
                    / LinearBicycle(nominal).steady_state_yaw_rate_gain(SPEED))
    ratios = {}
    for steer in (0.02, -0.02):
        _, base = _drive(None, steer=steer)
        _, pulled = _drive(pull, steer=steer)
        ratios[steer] = pulled[-1, 3] / base[-1, 3]
    print(f"yaw rate with FR x0.5 / nominal: left turn {ratios[0.02]:.4f}, right turn {ratios[-0.02]:.4f}, "
          f"linear bicycle with the front axle x0.75: {ratio_linear:.4f}")
    assert ratios[-0.02] < ratios[0.02] < 1.0
    assert ratios[0.02] == pytest.approx(ratio_linear, abs=0.02)


def test_start_s_and_the_gust_window():
    start = Disturbances(start_s=1.0, crosswind_force_n=800.0, crosswind_cp_m=0.6)
    _, plain = _drive(None, seconds=2.0)
    _, late = _drive(start, seconds=2.0)
    before = plain[:, 0] <= 1.0 + 1e-9
    assert np.array_equal(plain[before], late[before])
    assert late[-1, 5] > 0.05
    gust = Disturbances(gust_force_n=1500.0, gust_start_s=0.5, gust_duration_s=1.0, crosswind_cp_m=0.6)
    forces = [gust.gust_force(t) for t in (0.49, 0.5, 1.0, 1.5, 1.51)]
    assert forces == pytest.approx([0.0, 0.0, 1500.0, 0.0, 0.0], abs=1e-9)
    _, gusted = _drive(gust, seconds=4.0)
    assert np.array_equal(gusted[gusted[:, 0] <= 0.5 + 1e-9], plain[plain[:, 0] <= 0.5 + 1e-9])
    # The gust's lateral impulse (750 N s) moves the car sideways; after it the car keeps
    # the heading it was given (no restoring force on an open-loop car).
    print(f"gust 1500 N x 1 s: y at 4 s {gusted[-1, 5]:+.3f} m, yaw rate {gusted[-1, 3]:+.5f} rad/s")
    assert gusted[-1, 5] > 0.05 and abs(gusted[-1, 3]) < 1e-3


# ---------------------------------------------------------------------------- the table

def _scenario_file(tmp_path: Path, table: str) -> Path:
    text = (Path(__file__).resolve().parent.parent / "hil" / "scenarios" / "dlc_smoke.toml").read_text()
    text = text.replace('file = "../paths/dlc.csv"', f'file = "{DLC_PATH_FILE.as_posix()}"')
    file = tmp_path / "disturbed.toml"
    file.write_text(text + "\n[disturbances]\n" + table + "\n")
    return file


def test_the_table_loads_with_every_key(tmp_path):
    scenario = Scenario.load(_scenario_file(tmp_path, "\n".join([
        "start_s = 0.5", "steer_offset_rad = 0.01", "bank_angle_rad = 0.03", "crosswind_force_n = 400",
        "crosswind_cp_m = 0.6", "gust_force_n = 800.0", "gust_start_s = 1.0", "gust_duration_s = 1.0",
        "yaw_rate_bias_rad_s = 0.005", 'pull_wheel = "FR"', "pull_stiffness_scale = 0.7"])))
    d = scenario.disturbances
    assert (d.start_s, d.crosswind_force_n, d.pull_wheel, d.pull_stiffness_scale) == (0.5, 400.0, "FR", 0.7)
    print(d.describe())


@pytest.mark.parametrize("table, words", [
    ("bank_angle_rad = 3.0", ["disturbances.bank_angle_rad = 3.0", "[-0.15, 0.15]"]),
    ("steer_offset_rad = nan", ["disturbances.steer_offset_rad = nan", "finite"]),
    ("crosswind_force_n = \"400\"", ["disturbances.crosswind_force_n = '400'", "number"]),
    ("yaw_rate_bias = 0.01", ["unknown key", "disturbances.yaw_rate_bias"]),
    ("gust_force_n = 800.0", ["disturbances.gust_duration_s = 0.0", "> 0"]),
    ("pull_stiffness_scale = 0.7", ["disturbances.pull_stiffness_scale = 0.7", "pull_wheel"]),
    ("pull_wheel = \"XX\"\npull_stiffness_scale = 0.7", ["disturbances.pull_wheel = 'XX'", "FL, FR, RL, RR"]),
    ("pull_wheel = \"FL\"", ["disturbances.pull_wheel = 'FL'", "pull_stiffness_scale"]),
    ("pull_wheel = \"FL\"\npull_stiffness_scale = 0.0", ["disturbances.pull_stiffness_scale = 0.0", "[0.1, 2]"]),
    ("start_s = 2.0\ngust_force_n = 800.0\ngust_duration_s = 1.0\ngust_start_s = 1.0",
     ["disturbances.gust_start_s = 1.0", ">= start_s (2)"]),
    ("start_s = -1.0", ["disturbances.start_s = -1.0", "[0, 3600]"]),
])
def test_bad_values_are_refused_naming_file_field_and_value(tmp_path, table, words):
    file = _scenario_file(tmp_path, table)
    with pytest.raises(ScenarioError) as error:
        Scenario.load(file)
    message = str(error.value)
    print(message)
    assert message.startswith(str(file)) and all(word in message for word in words), message


def test_direct_construction_is_checked_too():
    with pytest.raises(DisturbanceError, match="crosswind_cp_m"):
        Disturbances(crosswind_cp_m=10.0)


# ---------------------------------------------------------------------------- HIL and runner

def test_hil_plant_node_and_closed_loop_runner_build_the_same_disturbed_plant(tmp_path):
    scenario = Scenario.load(_scenario_file(tmp_path, "steer_offset_rad = 0.01\nyaw_rate_bias_rad_s = 0.005\n"
                                                      "crosswind_force_n = 400.0\ncrosswind_cp_m = 0.6"))
    node = PlantNode(scenario)
    plant, command = default_plant(scenario)
    start = scenario.start
    plant.reset(vx=start.speed_mps, x=start.x_m, y=start.y_m, yaw=start.yaw_rad)
    # with vehicle faults the injector builds the plant: the disturbances stay on
    heavier = FaultInjector(FaultSpec.from_mapping({"vehicle": {"mass_offset_kg": 100.0}})).vehicle(scenario)
    misaligned = FaultInjector(FaultSpec.from_mapping({"vehicle": {"steer_offset_rad": 0.01}})).vehicle(scenario)
    assert isinstance(misaligned, OffsetSteeringVehicle)
    for vehicle in (node.vehicle, plant, heavier, misaligned):
        assert vehicle.disturbances == scenario.disturbances
    for tick in range(400):
        node.advance(tick * 5, TICK_S)
        plant.step(command(drive_torque=0.0, steer_angle=0.0), TICK_S)
    assert node.vehicle.outputs() == plant.outputs()
    frames = node.frames_due(2000)
    from can_defs.codec import decode
    reported = decode(frames[0].arbitration_id, bytes(frames[0].data)).frame.yaw_rate
    true_yaw_rate = node.vehicle.true_outputs().yaw_rate
    print(f"after 2 s: y {plant.outputs().y - start.y_m:+.3f} m, VEH_DYN YAW_RATE {reported:+.4f}, true "
          f"{true_yaw_rate:+.4f} rad/s")
    assert reported == pytest.approx(true_yaw_rate + 0.005, abs=2e-3)   # DBC resolution
    trace = node.trace()
    np.testing.assert_allclose(trace["steer"], 0.01)       # the trace has the true wheel angle


# ---------------------------------------------------------------------------- campaign axis

DISTURBANCE_GRID = """
name = "d"
[axes]
controller = ["lmpc"]
scenario = ["dlc_smoke"]
disturbance = ["none", "wind"]
[disturbances.wind]
crosswind_force_n = 400.0
crosswind_cp_m = 0.6
"""


def test_the_disturbance_axis_writes_the_table_into_each_cells_scenario(tmp_path):
    import tomllib

    from studies.campaign.grid import load_grid, to_toml
    from studies.campaign.runner import cell_key

    (tmp_path / "grid.toml").write_text(DISTURBANCE_GRID)
    grid = load_grid(tmp_path / "grid.toml")
    assert [c.disturbance for c in grid.cells] == ["none", "wind"]
    plain, windy = (grid.scenario_document(c) for c in grid.cells)
    assert "disturbances" not in plain
    assert windy["disturbances"] == {"crosswind_force_n": 400.0, "crosswind_cp_m": 0.6}
    file = tmp_path / "cell.toml"
    file.write_text(to_toml(windy))
    assert tomllib.loads(file.read_text()) == windy
    assert Scenario.load(file).disturbances == Disturbances(crosswind_force_n=400.0, crosswind_cp_m=0.6)
    # a "none" cell has the key it had before the axis existed
    (tmp_path / "plain.toml").write_text(DISTURBANCE_GRID.replace('disturbance = ["none", "wind"]\n', ""))
    before = load_grid(tmp_path / "plain.toml")
    assert cell_key(grid, grid.cells[0], "code") == cell_key(before, before.cells[0], "code")
    assert cell_key(grid, grid.cells[1], "code") != cell_key(grid, grid.cells[0], "code")


@pytest.mark.parametrize("change, words", [
    (('"wind"]', '"gale"]'), ["axes.disturbance value 'gale'", "[disturbances.NAME]"]),
    (("crosswind_cp_m = 0.6", "crosswind_cp_m = 60.0"), ["disturbances.wind", "crosswind_cp_m = 60.0"]),
    (("crosswind_cp_m = 0.6", "cp = 0.6"), ["disturbances.wind", "unknown key", "disturbances.cp"]),
])
def test_a_bad_disturbance_in_a_grid_is_an_error_naming_the_file_and_the_key(tmp_path, change, words):
    from studies.campaign.grid import GridError, load_grid

    file = tmp_path / "grid.toml"
    file.write_text(DISTURBANCE_GRID.replace(*change))
    with pytest.raises(GridError) as error:
        load_grid(file)
    print(error.value)
    assert str(error.value).startswith(str(file)) and all(w in str(error.value) for w in words)

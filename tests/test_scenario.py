"""hil.scenario and hil.path_files: shipped scenarios, the path file, validation errors."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from controller.reference import ReferencePath
from hil.errors import PathFileError, ScenarioError
from hil.metrics import path_errors
from hil.path_files import (DLC_PATH_FILE, DLC_X_END_M, DLC_X_START_M, DLC_X_STEP_M,
                            MAX_POINT_SPACING_M, double_lane_change,
                            double_lane_change_points, format_path_csv, read_path_csv,
                            write_path_csv)
from hil.scenario import SCENARIO_DIR, Scenario, list_scenarios, load_scenario

KMH = 1 / 3.6


# --- the shipped path -------------------------------------------------------------------


def test_shipped_path_equals_regenerated_one() -> None:
    """Regenerate with: python -m hil.path_files"""
    assert DLC_PATH_FILE.read_text() == format_path_csv(double_lane_change_points())


def test_shipped_path_meets_the_contract() -> None:
    text = DLC_PATH_FILE.read_text().splitlines()
    assert text[0] == "x,y,yaw"
    points = read_path_csv(DLC_PATH_FILE)
    spacing = np.hypot(np.diff(points[:, 0]), np.diff(points[:, 1]))
    print(f"{len(points)} points, spacing {spacing.min():.3f} .. {spacing.max():.3f} m, "
          f"X {points[0, 0]} .. {points[-1, 0]} m")
    assert spacing.max() <= MAX_POINT_SPACING_M
    assert np.all(np.diff(points[:, 0]) > 0)          # driving order, +X
    assert points[0, 0] <= -20.0 and points[-1, 0] >= 150.0


def test_formula_shape_and_yaw_is_the_tangent() -> None:
    x = np.linspace(-20, 150, 6801)
    y, yaw = double_lane_change(x)
    numeric = np.arctan(np.gradient(y, x))
    print(f"max |yaw - atan(dY/dX)| = {np.max(np.abs(yaw - numeric)):.2e} rad, "
          f"Y range {y.min():.3f} .. {y.max():.3f} m")
    assert np.max(np.abs(yaw - numeric)) < 1e-5
    # First lane change to ~ +4 m, then back beyond the start: Y -> 4.05 - 5.7 = -1.65 m.
    assert 3.5 < y.max() < 4.05
    assert y[-1] == pytest.approx(-1.65, abs=0.01)
    assert abs(y[0]) < 1e-3


def test_shipped_path_is_the_controllers_double_lane_change() -> None:
    """The shipped file, loaded as the ECU loads it, is `ReferencePath.double_lane_change`
    over the shipped extent (to the 6 decimals of the file)."""
    shipped = ReferencePath.from_csv(DLC_PATH_FILE)
    generated = ReferencePath.double_lane_change(DLC_X_START_M, DLC_X_END_M, DLC_X_STEP_M)
    assert shipped.x.size == generated.x.size
    gap = max(float(np.max(np.abs(a - b))) for a, b in
              ((shipped.x, generated.x), (shipped.y, generated.y), (shipped.yaw, generated.yaw)))
    print(f"shipped dlc.csv vs ReferencePath.double_lane_change: max difference {gap:.2e}")
    assert gap <= 5e-7


@pytest.mark.parametrize(
    "text, message",
    [
        ("x,y\n0,0\n0.5,0\n", "header"),
        ("x,y,yaw\n0,0,0\n", "at least 2 points"),
        ("x,y,yaw\n0,0,0\n0.4,0,abc\n", "not a number"),
        ("x,y,yaw\n0,0,0\n0.6,0,0\n", "0.600 m from the previous point"),
        ("x,y,yaw\n0,0,0\n0,0,0\n", "0.000 m from the previous point"),
        ("x,y,yaw\n0,0,0\n0.1,nan,0\n", "y = nan is not finite"),
        ("x,y,yaw\n0,0,0\n0.1,0\n", "line 3 has 2 columns"),
    ],
)
def test_bad_path_files_are_refused(tmp_path: Path, text: str, message: str) -> None:
    file = tmp_path / "p.csv"
    file.write_text(text)
    with pytest.raises(PathFileError, match=message):
        read_path_csv(file)


def test_path_round_trip_and_missing_file(tmp_path: Path) -> None:
    points = double_lane_change_points(0.0, 30.0, 0.4)
    write_path_csv(tmp_path / "p.csv", points)
    np.testing.assert_allclose(read_path_csv(tmp_path / "p.csv"), points, atol=5e-7)
    with pytest.raises(PathFileError, match="path file not found"):
        read_path_csv(tmp_path / "missing.csv")
    with pytest.raises(PathFileError, match="x_step"):
        double_lane_change_points(0.0, 10.0, 0.6)


# --- shipped scenarios ------------------------------------------------------------------


def test_shipped_scenarios_are_listed_and_load() -> None:
    names = list_scenarios()
    assert {"dlc_high_mu", "dlc_low_mu", "dlc_smoke", "straight_curve"} <= set(names)
    for name in names:
        scenario = load_scenario(name)
        assert scenario.name == name
        if name.startswith("dlc_"):
            assert scenario.path_file == DLC_PATH_FILE.resolve()


def test_high_mu_is_the_papers_first_case() -> None:
    scenario = load_scenario("dlc_high_mu")
    assert scenario.mu == 0.85 and scenario.mass_kg is None and scenario.mass_offset_kg == 0.0
    assert scenario.start.speed_mps == pytest.approx(35 * KMH)
    speeds = scenario.speed_profile.target_speeds(np.linspace(0, scenario.duration_s, 50))
    np.testing.assert_allclose(speeds, 35 * KMH)


def test_low_mu_is_the_papers_second_case() -> None:
    scenario = load_scenario("dlc_low_mu")
    assert scenario.mu == 0.5
    speeds = scenario.speed_profile.target_speeds(np.linspace(0, scenario.duration_s, 400))
    print(f"low-mu target {speeds.min() / KMH:.1f} .. {speeds.max() / KMH:.1f} km/h")
    assert scenario.target_speed(0.0) == pytest.approx(50 * KMH)
    assert scenario.start.speed_mps == pytest.approx(50 * KMH)
    assert speeds.min() == pytest.approx(45 * KMH) and speeds.max() == pytest.approx(55 * KMH)


@pytest.mark.parametrize("name", ["dlc_high_mu", "dlc_low_mu", "dlc_smoke"])
def test_scenarios_start_on_the_path_and_end_before_it(name: str) -> None:
    scenario = load_scenario(name)
    points = scenario.path_points()
    start = scenario.start
    errors = path_errors(np.array([[start.x_m, start.y_m, start.yaw_rad]]),
                         ReferencePath.from_csv(scenario.path_file))
    assert abs(errors.lateral_error[0]) < 0.01 and abs(errors.heading_error[0]) < 0.005
    assert start.x_m - points[0, 0] >= 10.0                     # path behind the start
    # Driving the target profile, the run plus a 1 s horizon at top speed stays on the path.
    t = np.linspace(0.0, scenario.duration_s, 2001)
    travelled = np.trapezoid(scenario.speed_profile.target_speeds(t), t)
    reach = start.x_m + travelled + max(scenario.speed_profile.speeds_mps) * 1.0
    print(f"{name}: X reach {reach:.1f} m of {points[-1, 0]:.1f} m")
    assert reach < points[-1, 0]


def test_short_scenario_is_ci_sized_and_steers() -> None:
    scenario = load_scenario("dlc_smoke")
    assert scenario.duration_s <= 5.0
    x_end = scenario.start.x_m + scenario.start.speed_mps * scenario.duration_s
    y_start, _ = double_lane_change(np.array([scenario.start.x_m]))
    y_end, _ = double_lane_change(np.array([x_end]))
    assert y_end[0] - y_start[0] > 3.0        # most of the first lane change is inside


def test_speed_profile_interpolates_and_holds() -> None:
    profile = load_scenario("dlc_low_mu").speed_profile
    assert profile.target_speed(1.5) == pytest.approx(52.5 * KMH)
    assert profile.target_speed(-1.0) == pytest.approx(50 * KMH)
    assert profile.target_speed(100.0) == pytest.approx(50 * KMH)


def test_vehicle_params_carry_mu_and_mass(tmp_path: Path) -> None:
    from models.vehicle_params import load_vehicle_params

    nominal = load_vehicle_params()
    file = _write(tmp_path, VALID.replace("mass_offset_kg = 0.0", "mass_offset_kg = 200.0"))
    params = Scenario.load(file).vehicle_params()
    assert params.mu == 0.85 and params.mass == pytest.approx(nominal.mass + 200.0)
    absolute = Scenario.load(_write(tmp_path, VALID.replace("mass_offset_kg = 0.0",
                                                            "mass_kg = 1700.0")))
    assert absolute.vehicle_params().mass == 1700.0
    rear = Scenario.load(_write(tmp_path, VALID.replace(
        "mass_offset_kg = 0.0", 'mass_offset_kg = 0.0\nvariant = "van"\ncornering_stiffness_rear_scale = 0.8')))
    from models.vehicle_variants import load_variant

    van = load_variant("van").params
    assert rear.vehicle_params().cornering_stiffness_rear_scale == pytest.approx(
        0.8 * van.cornering_stiffness_rear_scale)
    assert rear.vehicle_params().mass == van.mass
    as_it_is = Scenario.load(_write(tmp_path, VALID)).vehicle_params()
    assert as_it_is.cornering_stiffness_rear_scale == nominal.cornering_stiffness_rear_scale


# --- validation -------------------------------------------------------------------------

VALID = f"""
name = "t"
duration_s = 2.0
[path]
id = 3
file = "{DLC_PATH_FILE.as_posix()}"
[road]
mu = 0.85
[vehicle]
mass_offset_kg = 0.0
[start]
x_m = 0.0
y_m = 0.0
yaw_rad = 0.0
speed_kmh = 35.0
[speed_profile]
time_s = [0.0, 1.0]
target_speed_kmh = [35.0, 40.0]
"""


def _write(tmp_path: Path, text: str) -> Path:
    file = tmp_path / "scenario.toml"
    file.write_text(text)
    return file


def test_valid_file_loads_with_si_units(tmp_path: Path) -> None:
    scenario = Scenario.load(_write(tmp_path, VALID))
    assert scenario.path_id == 3 and scenario.duration_s == 2.0
    assert scenario.speed_profile.speeds_mps == pytest.approx((35 * KMH, 40 * KMH))
    assert dict(scenario.faults) == {}
    hash(scenario)  # frozen and usable as a key


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("mu = 0.85", "mu = -0.1", r"road.mu = -0.1: must be in \[0.05, 1.5\]"),
        ("mu = 0.85", 'mu = "high"', r"road.mu = 'high': must be a number"),
        ("mu = 0.85", "mu = nan", "road.mu = nan: must be finite"),
        ("mu = 0.85", "muu = 0.85", "unknown field.*road.muu"),
        ('name = "t"', "", "missing field name"),
        ("duration_s = 2.0", "duration_s = 0.0", "duration_s = 0.0"),
        ("id = 3", "id = 300", r"path.id = 300: must be in \[0, 255\]"),
        ("id = 3", "id = 1.5", "path.id = 1.5: must be an integer"),
        (DLC_PATH_FILE.as_posix(), "nowhere.csv", "path.file = 'nowhere.csv'.*path file not found"),
        ("speed_kmh = 35.0", "speed_kmh = 350.0", "start.speed_kmh = 350.0"),
        ("yaw_rad = 0.0", "yaw_rad = 4.0", "start.yaw_rad = 4.0"),
        ("time_s = [0.0, 1.0]", "time_s = [1.0, 1.0]", "speed_profile.time_s .* increasing"),
        ("time_s = [0.0, 1.0]", "time_s = [0.0]", "has 1 points .* has 2"),
        ("time_s = [0.0, 1.0]", "time_s = []", "speed_profile.time_s = \\[\\]: must be a non"),
        ("target_speed_kmh = [35.0, 40.0]", "target_speed_kmh = [35.0, -1.0]",
         "target_speed_kmh = -1.0"),
        ("mass_offset_kg = 0.0", "mass_offset_kg = 0.0\nmass_kg = 1600.0", "exclusive"),
        ("mass_offset_kg = 0.0", "mass_kg = 16.0", "vehicle.mass_kg = 16.0"),
        ("mass_offset_kg = 0.0", "mass_offset_kg = 0.0\ncornering_stiffness_rear_scale = 80.0",
         "vehicle.cornering_stiffness_rear_scale = 80.0"),
        ("[road]", "[roads]", "unknown field.*roads"),
        ("[road]\nmu = 0.85", "", "missing field road"),
        ("mu = 0.85", "mu = 0.85 0.9", "invalid TOML"),
    ],
)
def test_invalid_fields_are_named_with_their_value(tmp_path: Path, old: str, new: str,
                                                   message: str) -> None:
    assert old in VALID
    file = _write(tmp_path, VALID.replace(old, new, 1))
    with pytest.raises(ScenarioError, match=message) as info:
        Scenario.load(file)
    print(info.value)
    assert str(file) in str(info.value)



def test_a_copied_scenario_finds_its_path_file_relative_to_the_repository(tmp_path: Path) -> None:
    """Issue 39 item 4: a shipped scenario copied into another folder names its path file
    relative to the repository (docs/identification.md section 2); a path found in neither
    place names both places tried."""
    shipped = SCENARIO_DIR / "identification" / "drive.toml"
    text = shipped.read_text()
    assert "file = \"../../paths/identification.csv\"" in text
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    copy = folder / "drive.toml"
    copy.write_text(text.replace("../../paths/identification.csv", "hil/paths/identification.csv")
                    .replace("mu = 0.85", "mu = 0.5"))
    scenario = load_scenario(copy)
    assert scenario.path_file == load_scenario(shipped).path_file and scenario.mu == 0.5
    copy.write_text(text)  # the shipped relative path, which only works beside the original
    with pytest.raises(ScenarioError) as info:
        load_scenario(copy)
    print(info.value)
    message = str(info.value)
    assert "path.file = '../../paths/identification.csv': path file not found" in message
    assert str((folder / "../../paths/identification.csv").resolve()) in message
    assert "nor to the repository" in message
    # beside the scenario file comes first
    (folder / "hil" / "paths").mkdir(parents=True)
    write_path_csv(folder / "hil" / "paths" / "identification.csv", double_lane_change_points())
    copy.write_text(text.replace("../../paths/identification.csv", "hil/paths/identification.csv"))
    assert load_scenario(copy).path_file == (folder / "hil" / "paths" / "identification.csv").resolve()

def test_faults_table_is_kept_raw_and_read_only(tmp_path: Path) -> None:
    text = VALID + '\n[faults]\nkind = "drop"\n[[faults.events]]\nframe = "VEH_DYN"\nat_s = 1.5\n'
    scenario = Scenario.load(_write(tmp_path, text))
    assert scenario.faults["kind"] == "drop"
    assert scenario.faults["events"] == [{"frame": "VEH_DYN", "at_s": 1.5}]
    with pytest.raises(TypeError):
        scenario.faults["kind"] = "other"  # type: ignore[index]


def test_missing_and_unknown_scenarios(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="cannot read"):
        Scenario.load(tmp_path / "none.toml")
    with pytest.raises(ScenarioError, match="unknown scenario 'dlc_nope'.*dlc_high_mu"):
        load_scenario("dlc_nope")
    assert load_scenario(SCENARIO_DIR / "dlc_smoke.toml").name == "dlc_smoke"
    assert math.isfinite(load_scenario("dlc_smoke").duration_s)

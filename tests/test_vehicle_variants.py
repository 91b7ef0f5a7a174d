"""Vehicle variants (models/vehicle_variants.toml, models/vehicle_variants.py): loading and
its errors, the scenario's ``[vehicle] variant`` over CAN and without, each variant's plant
against its own linear bicycle, and the study (studies/vehicle_variants.py) end to end on
its smoke settings."""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from hil.errors import ScenarioError
from hil.scenario import SCENARIO_DIR, load_scenario
from models.bicycle import LinearBicycle, nominal_model_params
from models.vehicle_params import load_vehicle_params, params_as_dict
from models.vehicle_variants import (DEFAULT_VARIANTS_PATH, VehicleVariantError, load_variant, load_variants,
                                     variant_names)

SHIPPED = ("light", "heavy", "van", "winter_tyres")


# --- the shipped variants -----------------------------------------------------------------


def test_the_shipped_variants_load_and_each_changes_the_car():
    nominal = params_as_dict(load_vehicle_params())
    assert variant_names() == SHIPPED
    for name, variant in load_variants().items():
        params = params_as_dict(variant.params)
        changed = {k for k in nominal if nominal[k] != params[k]}
        print(f"{name}: {variant.description}; changed {sorted(changed)}")
        assert changed == set(variant.overrides) and changed
        assert variant.params.mu == nominal["mu"]  # the road's, not the car's


def test_every_value_of_the_shipped_file_has_its_source_comment_above():
    """A comment opens each block of at most two values (lf and lr share one)."""
    values_since_comment: int | None = None  # None: no comment since the last table header
    values = 0
    for number, line in enumerate(DEFAULT_VARIANTS_PATH.read_text().splitlines(), 1):
        text = line.strip()
        if text.startswith("#"):
            values_since_comment = 0
        elif text.startswith("["):
            values_since_comment = None
        elif re.match(r"[a-z_]+ = ", text) and not text.startswith("description = "):
            assert values_since_comment is not None and values_since_comment < 2, \
                f"line {number} has no source comment above it: {text}"
            values_since_comment += 1
            values += 1
    assert values == sum(len(v.overrides) for v in load_variants().values())


def test_the_variants_are_the_cars_the_issue_asks_for():
    variants = {name: v.params for name, v in load_variants().items()}
    nominal = load_vehicle_params()
    assert variants["light"].mass < nominal.mass < variants["heavy"].mass < variants["van"].mass
    van = variants["van"]
    assert van.cg_height > 1.5 * nominal.cg_height and van.wheelbase > nominal.wheelbase + 0.5
    assert van.yaw_inertia > 3 * nominal.yaw_inertia
    tyres = variants["winter_tyres"]
    assert tyres.cornering_stiffness_factor < nominal.cornering_stiffness_factor
    assert tyres.shape_lateral != nominal.shape_lateral
    assert (tyres.mass, tyres.lf, tyres.yaw_inertia) == (nominal.mass, nominal.lf, nominal.yaw_inertia)


# --- errors name the file, the field and the value ------------------------------------------


def _variants_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "variants.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("body, expected", [
    ('[x.body]\nmass = -5.0', "x.body.mass = -5.0: outside (0.0, inf]"),
    ('[x.body]\nmass = 1.6', "x.body.mass = 1.6: outside the plausible [300, 5000] kg"),
    ('[x.body]\nlf = 1200.0', "x.body.lf = 1200.0: outside the plausible"),
    ('[x.tyre]\nmass = 1500.0', "x.tyre.mass = 1500.0: it belongs in [body]"),
    ('[x.body]\nweight = 1500.0', "x.body.weight = 1500.0: unknown vehicle parameter"),
    ('[x.body]\nlf = "1.2"', "x.body.lf = '1.2': must be a finite number"),
    ('[x.body]\nlf = nan', "x.body.lf = nan: must be a finite number"),
    ('[x.tyre]\nmu = 0.3', "x.tyre.mu = 0.3: the road friction is the scenario's"),
    ('[x.tyre]\nshape_lateral = 2.5', "x.tyre.shape_lateral = 2.5: outside (1.0, 2.0]"),
    ('[x.tyre]\ncornering_stiffness_rear_scale = 0.0', "x.tyre.cornering_stiffness_rear_scale = 0.0: outside"),
    ('[x.chassis]\nmass = 1500.0', "x.chassis: not a section of vehicle.toml"),
    ('[x.body]\nyaw_inertia = 500.0', "x.body.yaw_inertia = 500.0: radius of gyration"),
    ('[x.simulation]\nblend_speed_high = 0.4', "x.simulation.blend_speed_high = 0.4: must exceed blend_speed_low 0.5"),
    ('', "x: no value changed"),
])
def test_a_bad_value_is_one_error_naming_file_field_and_value(tmp_path, body, expected):
    path = _variants_file(tmp_path, f'[x]\ndescription = "a car"\n{body}\n')
    with pytest.raises(VehicleVariantError) as error:
        load_variants(path)
    print(error.value)
    assert str(error.value).startswith(f"{path}: ") and expected in str(error.value)


@pytest.mark.parametrize("text, expected", [
    ('[x.body]\nmass = 1500.0\n', "x.description = None: must be a non-empty string"),
    ('x = 3\n', "x = 3: a variant is a [x] table"),
    ('[Van]\ndescription = "v"\n[Van.body]\nmass = 1500.0\n', "[Van]: a variant's name is lower case"),
    ('[x\n', "invalid TOML"),
])
def test_a_bad_variant_table_is_one_error_naming_the_file(tmp_path, text, expected):
    path = _variants_file(tmp_path, text)
    with pytest.raises(VehicleVariantError, match=re.escape(expected)) as error:
        load_variants(path)
    assert str(error.value).startswith(f"{path}: ")


def test_a_missing_file_and_an_unknown_name_are_named(tmp_path):
    with pytest.raises(VehicleVariantError, match="variants file not found"):
        load_variants(tmp_path / "none.toml")
    with pytest.raises(VehicleVariantError, match="unknown vehicle variant 'bus'; one of light, heavy, van"):
        load_variant("bus")


# --- scenarios select a variant --------------------------------------------------------------


def _scenario_file(tmp_path: Path, vehicle: str, base: str = "dlc_low_mu") -> Path:
    text = (SCENARIO_DIR / f"{base}.toml").read_text()
    text = text.replace('"../paths/', f'"{SCENARIO_DIR.parent / "paths"}/')
    if "[vehicle]" in text:
        text = re.sub(r"\[vehicle\]\n[^\[]*", f"[vehicle]\n{vehicle}\n\n", text)
    else:
        text += f"\n[vehicle]\n{vehicle}\n"
    path = tmp_path / f"{base}_variant.toml"
    path.write_text(text)
    return path


def test_a_scenario_selects_a_variant_with_its_own_mu_and_mass_offset(tmp_path):
    van = load_variant("van").params
    scenario = load_scenario(_scenario_file(tmp_path, 'variant = "van"\nmass_offset_kg = 100.0'))
    assert scenario.vehicle_variant == "van"
    params = scenario.vehicle_params()
    assert params == dataclasses.replace(van, mu=0.5, mass=van.mass + 100.0)
    assert scenario.vehicle().params == params
    nominal = load_scenario("dlc_low_mu")
    assert nominal.vehicle_variant is None
    assert nominal.vehicle_params() == load_vehicle_params(mu=0.5)


def test_an_unknown_variant_in_a_scenario_names_file_field_and_value(tmp_path):
    path = _scenario_file(tmp_path, 'variant = "bus"')
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    print(error.value)
    assert str(error.value).startswith(f"{path}: vehicle.variant = 'bus': ")
    assert "one of light, heavy, van, winter_tyres" in str(error.value)


def test_the_hil_plant_node_and_the_fault_injector_build_the_variant(tmp_path):
    from hil.fault_injector import FaultInjector
    from hil.faults import FaultSpec, VehicleFaults
    from hil.plant_node import PlantNode

    scenario = load_scenario(_scenario_file(tmp_path, 'variant = "light"'))
    assert PlantNode(scenario).vehicle.params == scenario.vehicle_params()
    faulty = FaultInjector(FaultSpec(vehicle=VehicleFaults(mass_offset_kg=200.0))).vehicle(scenario)
    assert faulty.params.mass == load_variant("light").params.mass + 200.0
    assert faulty.params.yaw_inertia == load_variant("light").params.yaw_inertia


def test_eso_hil_run_drives_the_variant_over_can(tmp_path, capsys):
    from hil.__main__ import main

    finals = {}
    for name, vehicle in (("nominal", "mass_offset_kg = 0.0"), ("van", 'variant = "van"')):
        folder = tmp_path / name
        folder.mkdir()
        scenario = _scenario_file(folder, vehicle, base="dlc_smoke")
        assert main(["run", "--scenario", str(scenario), "--controller", "lmpc", "--out", str(folder)]) == 0
        summary = json.loads((folder / "summary.json").read_text())
        finals[name] = summary["tracking"]["lateral_error_m"]["rmse"]
    capsys.readouterr()
    print(f"dlc_smoke over CAN, LMPC e_Y RMSE: {finals}")
    assert finals["van"] != finals["nominal"]


# --- each variant's plant is the car it describes ----------------------------------------------


@pytest.mark.slow
def test_each_variants_plant_has_its_own_bicycles_yaw_gain_and_not_the_nominal_ones():
    """Steady turns at 10-20 m/s and a small steer (0.005 rad, linear range): the plant's
    yaw-rate gain is its own linear bicycle's vx / (L + K_us vx^2) within 3 %; the van and
    the winter tyres, whose gains differ from the nominal car's by more than 5 %, are
    told apart from it."""
    from models.vehicle import YAW_RATE
    from studies.handling import steady_state

    speeds = np.array([10.0, 15.0, 20.0])
    nominal_bicycle = LinearBicycle(nominal_model_params())
    for name, variant in load_variants().items():
        own = LinearBicycle(nominal_model_params(variant.params))
        state, steady = steady_state(variant.params, 0.85, speeds, np.full(3, 0.005))
        gain = state[:, YAW_RATE] / 0.005
        expected = np.array([own.steady_state_yaw_rate_gain(v) for v in speeds])
        nominal = np.array([nominal_bicycle.steady_state_yaw_rate_gain(v) for v in speeds])
        print(f"{name}: plant {np.round(gain, 3)}, own bicycle {np.round(expected, 3)}, "
              f"nominal bicycle {np.round(nominal, 3)}")
        assert steady.all()
        assert gain == pytest.approx(expected, rel=0.03)
        if np.max(np.abs(expected / nominal - 1.0)) > 0.05:
            assert np.max(np.abs(gain / nominal - 1.0)) > 0.05


def test_the_winter_tyres_corner_softer_and_peak_at_a_larger_slip():
    from models.tyre import tyre_forces

    nominal, winter = load_vehicle_params(), load_variant("winter_tyres").params
    ratio = nominal_model_params(winter).cornering_stiffness_front / nominal_model_params().cornering_stiffness_front
    assert ratio == pytest.approx(12.0 / 17.0, rel=1e-4)
    slip = np.tan(np.radians(np.linspace(0.1, 20.0, 2000)))
    peaks = {}
    for name, params in (("nominal", nominal), ("winter", winter)):
        _, fy = tyre_forces(np.zeros_like(slip), slip, np.full_like(slip, 4000.0), 0.85, params)
        peaks[name] = (np.degrees(np.arctan(slip[np.argmax(fy)])), fy.max())
    print(f"peak slip angle (deg), force (N): {peaks}")
    assert peaks["winter"][0] > peaks["nominal"][0] + 2.0
    assert peaks["winter"][1] == pytest.approx(peaks["nominal"][1], rel=1e-3)  # mu Fz stays


def test_a_heavier_car_accelerates_less_on_the_same_torque():
    from models.vehicle import FourWheelVehicle, VehicleCommand

    accelerations = {}
    for name in ("light", None, "van"):
        params = load_variant(name).params if name else load_vehicle_params()
        car = FourWheelVehicle(params)
        car.reset(vx=10.0)
        for _ in range(40):
            out = car.step(VehicleCommand(drive_torque=800.0, steer_angle=0.0), 0.025)
        accelerations[name or "nominal"] = (out.vx - 10.0) / 1.0
    print(f"mean acceleration over 1 s at 800 N m (m/s^2): {accelerations}")
    assert accelerations["light"] > accelerations["nominal"] > accelerations["van"]


# --- the study ----------------------------------------------------------------------------------


def test_the_measured_vehicle_file_has_the_variants_mass_and_axles_and_nominal_tyres(tmp_path):
    from studies.identification import measured_vehicle_file
    from studies.vehicle_variants import MEASURED_FIELDS

    van = load_variant("van").params
    file = measured_vehicle_file(tmp_path / "v.toml", {k: getattr(van, k) for k in MEASURED_FIELDS})
    written, nominal = params_as_dict(load_vehicle_params(file)), params_as_dict(load_vehicle_params())
    assert {k for k in nominal if written[k] != nominal[k]} == set(MEASURED_FIELDS)
    assert all(written[k] == getattr(van, k) for k in MEASURED_FIELDS)


def test_the_report_marks_lost_runs_and_checks_the_low_friction_goal():
    from studies.vehicle_variants_report import cell, low_friction_goal

    def run(controller, model, rmse, completed=True):
        return {"friction": "low", "controller": controller, "model": model, "completed": completed,
                "failure": None if completed else "|e_Y| = 10.1 m > 10.0 m", "duration_s": 8.2,
                "tracking": {"lateral_error_m": {"rmse": rmse}}}

    lost = run("eso-dkmpc", "nominal", 2.49, completed=False)
    assert cell(lost) == "lost at 8.2 s (2.49)" and cell(None) == "-"
    goal = low_friction_goal([{"variant": "van", "runs": [lost, run("eso-dkmpc", "identified", 0.02),
                                                          run("nmpc", "nominal", 0.03)]},
                              {"variant": "light", "runs": [run("eso-dkmpc", "nominal", 0.04),
                                                            run("eso-dkmpc", "identified", 0.05),
                                                            run("nmpc", "nominal", 0.03)]}])
    print("\n".join(goal))
    assert goal[0].endswith("holds (identified model).") and goal[1].endswith("does not hold.")


def test_an_unknown_variant_is_refused_before_anything_runs(tmp_path, capsys):
    from studies.vehicle_variants import main

    assert main(["--variants", "bus", "--out", str(tmp_path)]) == 2
    assert "--variants: unknown bus; one of light, heavy, van, winter_tyres" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_the_smoke_study_runs_end_to_end(tmp_path):
    """About 35 s on 2 shared cores: nominal-car reference runs, one variant's nominal runs,
    its 70 s drive over CAN, one short training epoch, the identified runs, the report."""
    from controller.registry import GEOMETRIC_NAMES
    from studies.vehicle_variants import main

    assert main(["--smoke", "--variants", "winter_tyres", "--out", str(tmp_path),
                 "--work", str(tmp_path / "work")]) == 0
    document = json.loads((tmp_path / "vehicle_variants.json").read_text())
    cars = {car["variant"]: car for car in document["cars"]}
    assert list(cars) == ["nominal", "winter_tyres"]
    runs = cars["winter_tyres"]["runs"]
    keys = {(r["friction"], r["controller"], r["model"]) for r in runs}
    nominal_controllers = {"eso-dkmpc", "dkmpc", "lmpc", "nmpc", *GEOMETRIC_NAMES}
    assert keys == ({(f, c, "nominal") for f in ("high", "low") for c in nominal_controllers}
                    | {(f, c, "identified") for f in ("high", "low") for c in ("eso-dkmpc", "dkmpc", "lmpc")})
    assert all(r["completed"] for r in runs)
    assert cars["winter_tyres"]["drive"]["frames_logged"] > 0
    assert (tmp_path / "work" / "winter_tyres" / "model" / "bicycle.json").is_file()
    text = (tmp_path / "vehicle_variants.md").read_text()
    assert "**Smoke settings**" in text and "| winter_tyres |" in text
    assert (tmp_path / "vehicle_variants.png").stat().st_size > 10_000

"""One implementation of each shared piece: the vehicle measurement record, the angle
wrap, the path CSV reader and formula, and the solver status against the contract's
QP_STATUS."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from can_defs.dbc import load_database
from can_defs.frames import FrameId, QpStatus
from controller import dead_reckoning, reference
from controller.base import SolverStatus, VehicleSample
from controller.errors import PathError
from firmware_sim.rx import PlantMeasurement
from hil import metrics, path_files
from hil.errors import PathFileError
from models import vehicle
from models.measurement import MEASUREMENT_FIELDS, VehicleMeasurement, wrap_angle

EIGHT = dict(vx=10.0, vy=0.1, yaw_rate=0.02, x=1.0, y=2.0, yaw=0.3, steer_angle=0.01,
             drive_torque=100.0)


def test_the_plant_controller_and_ecu_records_are_one_type() -> None:
    assert vehicle.VehicleOutputs is VehicleMeasurement
    assert MEASUREMENT_FIELDS == ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle",
                                  "drive_torque")
    # The controller's record adds the set point and, keyword only, the sample's age at the task
    # start (delay compensation); positional construction stays the nine values.
    for record, extra in ((VehicleSample, ("target_speed", "sample_age_s")), (PlantMeasurement, ("counter",))):
        assert issubclass(record, VehicleMeasurement)
        assert tuple(f.name for f in dataclasses.fields(record)) == MEASUREMENT_FIELDS + extra
    assert [f.name for f in dataclasses.fields(VehicleSample) if f.kw_only] == ["sample_age_s"]
    assert VehicleSample(*EIGHT.values(), 9.7).sample_age_s == 0.0


def test_sample_from_a_measurement_keeps_every_field_and_positional_order() -> None:
    plant = PlantMeasurement(**EIGHT, counter=7)
    sample = VehicleSample.from_measurement(plant, target_speed=9.7)
    assert type(sample) is VehicleSample
    assert sample == VehicleSample(*EIGHT.values(), 9.7)  # positional order unchanged
    assert sample.measurement_values() == plant.measurement_values() == EIGHT
    np.testing.assert_array_equal(sample.pose(), [1.0, 2.0, 0.3])
    np.testing.assert_array_equal(sample.state(), [10.0, 0.1, 0.02])


def test_plant_outputs_are_the_shared_record_with_yaw_wrapped() -> None:
    plant = vehicle.FourWheelVehicle()
    plant.reset(vx=10.0, yaw=3 * math.pi)
    outputs = plant.outputs()
    assert type(outputs) is VehicleMeasurement
    assert outputs.yaw == pytest.approx(-math.pi)


def test_wrap_angle_is_one_function_everywhere() -> None:
    assert reference.wrap_angle is wrap_angle
    assert dead_reckoning.wrap_angle is wrap_angle
    assert metrics.wrap_angle is wrap_angle


@pytest.mark.parametrize("angle, expected", [
    (math.pi, -math.pi), (-math.pi, -math.pi), (-3 * math.pi / 2, math.pi / 2),
    (3 * math.pi + 0.1, -math.pi + 0.1), (7.0, 7.0 - 2 * math.pi), (0.0, 0.0),
])
def test_wrap_angle_range_and_values(angle: float, expected: float) -> None:
    wrapped = wrap_angle(angle)
    assert isinstance(wrapped, float) and -math.pi <= wrapped < math.pi
    assert wrapped == pytest.approx(expected, abs=1e-12)


def test_wrap_angle_keeps_angles_inside_the_range_bit_for_bit() -> None:
    inside = np.array([-math.pi, -3.0, -1e-17, 0.1, 1.234567890123, math.pi - 1e-15])
    assert all(wrap_angle(float(a)) == a for a in inside)
    np.testing.assert_array_equal(wrap_angle(inside), inside)
    mixed = np.array([[0.1, 4.0], [-4.0, 2 * math.pi]])
    wrapped = wrap_angle(mixed)
    assert wrapped.shape == (2, 2) and wrapped[0, 0] == 0.1
    np.testing.assert_allclose(wrapped, [[0.1, 4.0 - 2 * math.pi], [2 * math.pi - 4.0, 0.0]],
                               atol=1e-12)


def test_hil_path_files_use_the_controllers_formula_and_reader(tmp_path: Path) -> None:
    assert path_files.double_lane_change is reference.double_lane_change_curve
    file = tmp_path / "bad.csv"
    file.write_text("x,y,yaw\n0,0,0\n0.6,0,0\n")
    with pytest.raises(PathError) as from_controller:
        reference.read_path_csv(file)
    with pytest.raises(PathFileError) as from_hil:
        path_files.read_path_csv(file)
    print(from_hil.value)
    assert str(from_hil.value) == str(from_controller.value)
    assert isinstance(from_hil.value.__cause__, PathError)


def test_csv_writer_round_trips_through_both_loaders(tmp_path: Path) -> None:
    points = path_files.double_lane_change_points(0.0, 20.0, 0.25)
    path_files.write_path_csv(tmp_path / "p.csv", points)
    loaded = reference.ReferencePath.from_csv(tmp_path / "p.csv")
    np.testing.assert_allclose(np.column_stack([loaded.x, loaded.y, loaded.yaw]), points, atol=5e-7)
    np.testing.assert_array_equal(reference.read_path_csv(tmp_path / "p.csv"),
                                  path_files.read_path_csv(tmp_path / "p.csv"))


def test_solver_status_is_the_contracts_qp_status() -> None:
    """One enum: controller.base.SolverStatus is can_defs.frames.QpStatus (the contract's
    CTRL_DIAG.QP_STATUS, which the ECU sends as the law gives it), and its names and values
    are the DBC's choices."""
    assert SolverStatus is QpStatus
    solver = [(member.name, int(member)) for member in SolverStatus]
    print("SolverStatus:", solver)
    choices = load_database().get_message_by_frame_id(FrameId.CTRL_DIAG) \
        .get_signal_by_name("QP_STATUS").choices
    assert {int(value): str(name) for value, name in choices.items()} == dict(
        (value, name) for name, value in solver)

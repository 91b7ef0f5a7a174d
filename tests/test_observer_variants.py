"""The variants of make observer-variants: each changes the one thing its name says."""
from __future__ import annotations

import numpy as np

from controller.base import VehicleSample
from controller.reference import ReferencePath
from studies.observer_variants import CASES, LateralRowsOnly, report, variants


def _step(controller, sample: VehicleSample):
    controller.set_path(ReferencePath.double_lane_change())
    return controller.step(sample)


def test_every_variant_builds_and_steps_within_the_limits() -> None:
    sample = VehicleSample(10.0, 0.05, 0.02, 0.0, 0.1, 0.0, 0.01, 0.0, 10.0)
    built = {name: build() for name, build in variants().items()}
    for name, controller in built.items():
        command, _ = _step(controller, sample)
        assert abs(command.steer_angle) <= 0.3, name
    assert built["no innovation bound"].tuning.eso_innovation_limit == 0.0
    assert built["bias estimate off"].tuning.yaw_rate_bias_pole == 1.0
    shipped = built["ESO-DKMPC (shipped)"].tuning
    assert built["fixed bound (no widening)"].tuning.eso_innovation_persistence == 0.0
    assert built["widening at any lateral acceleration"].tuning.eso_widening_lateral_accel == 0.0
    assert built["widening at any lateral acceleration"].tuning.eso_innovation_persistence == \
        shipped.eso_innovation_persistence
    assert built["ESO-DKMPC (shipped)"].tuning.eso_innovation_limit > 0.0
    assert built["slip target 0.02 / 0.003"].tuning.slip_target_limit == 0.02


def test_lateral_rows_only_drops_the_estimate_on_every_other_row() -> None:
    controller = variants()["w on vy, yaw rate only"]()
    assert isinstance(controller, LateralRowsOnly)
    sample = VehicleSample(10.0, 0.05, 0.02, 0.0, 0.1, 0.0, 0.01, 0.0, 10.0)
    _step(controller, sample)
    estimate = controller.disturbance(controller.lifted_state + 0.01)
    assert np.count_nonzero(estimate[[0, *range(3, estimate.size)]]) == 0
    assert np.count_nonzero(estimate[[1, 2]]) == 2


def test_the_course_angle_variant_steers_otherwise_than_the_heading_cost() -> None:
    sample = VehicleSample(10.0, 0.3, 0.02, 0.0, 0.3, 0.02, 0.01, 0.0, 10.0)  # a clear side-slip
    built = variants()
    shipped, _ = _step(built["ESO-DKMPC (shipped)"](), sample)
    course, _ = _step(built["course-angle cost"](), sample)
    assert abs(course.steer_angle - shipped.steer_angle) > 1e-4


def test_report_marks_runs_that_did_not_complete() -> None:
    cells = {label: (0.01, 0.002) for label, _, _ in CASES}
    cells[CASES[0][0]] = (float("nan"), float("nan"))
    text = report({"X": cells})
    assert "| X | - | 1.00 / +0.20 |" in text

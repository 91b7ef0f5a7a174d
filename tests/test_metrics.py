"""hil.metrics on geometry with known answers (the projection is controller.reference's)."""
from __future__ import annotations

import numpy as np
import pytest

from controller.reference import ReferencePath
from hil.errors import MetricsError
from hil.metrics import ComputeTimeStats, ErrorStats, path_errors, tracking_metrics, wrap_angle


def straight_path(yaw: float = 0.0, length: float = 50.0, spacing: float = 0.4) -> ReferencePath:
    """Straight line from the origin with heading ``yaw``."""
    s = np.arange(0.0, length + spacing / 2, spacing)
    return ReferencePath.from_arrays(s * np.cos(yaw), s * np.sin(yaw), np.full_like(s, yaw))


def circle_path(radius: float, n: int = 720) -> ReferencePath:
    """Counter-clockwise half circle about the origin starting at (R, 0)."""
    angle = np.linspace(0.0, np.pi, n)
    return ReferencePath.from_arrays(radius * np.cos(angle), radius * np.sin(angle),
                                     angle + np.pi / 2)


def project_onto_path(points: np.ndarray, path: ReferencePath):
    """Path errors of positions (n, 2) with yaw 0."""
    return path_errors(np.column_stack([points, np.zeros(len(points))]), path)


@pytest.mark.parametrize("offset", [-1.7, -0.2, 0.0, 0.35, 2.0])
@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_straight_path_constant_offset_gives_that_offset(offset: float, yaw: float) -> None:
    path = straight_path(yaw)
    s = np.linspace(1.0, 45.0, 37)
    left = np.array([-np.sin(yaw), np.cos(yaw)])
    points = np.column_stack([s * np.cos(yaw), s * np.sin(yaw)]) + offset * left
    projection = project_onto_path(points, path)
    worst = np.max(np.abs(projection.lateral_error - offset))
    print(f"yaw {yaw}, offset {offset}: max |e_Y - offset| = {worst:.2e} m")
    assert worst < 1e-12
    np.testing.assert_allclose(projection.progress, s, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(projection.heading_error + yaw), 0.0, atol=1e-12)


def test_beyond_the_ends_the_error_is_to_the_end_tangent_line() -> None:
    path = straight_path(0.0, length=10.0)
    points = np.array([[-5.0, 0.3], [15.0, -0.4]])
    projection = project_onto_path(points, path)
    np.testing.assert_allclose(projection.lateral_error, [0.3, -0.4], atol=1e-12)
    np.testing.assert_allclose(projection.progress, [0.0, 10.0], atol=1e-12)


@pytest.mark.parametrize("radius_of_point", [8.0, 9.5, 10.0, 10.6, 13.0])
def test_circle_lateral_error_is_radius_difference_left_positive(radius_of_point: float) -> None:
    radius = 10.0
    path = circle_path(radius)
    angle = np.linspace(0.2, np.pi - 0.2, 50)
    points = radius_of_point * np.column_stack([np.cos(angle), np.sin(angle)])
    projection = project_onto_path(points, path)
    # Driving counter-clockwise, the centre is on the left: inside = positive e_Y.
    expected = radius - radius_of_point
    # The polyline's chords sag R (1 - cos(dtheta / 2)) inside the true circle.
    sag = radius * (1.0 - np.cos(np.pi / 719 / 2))
    worst = np.max(np.abs(projection.lateral_error - expected))
    print(f"point radius {radius_of_point}: max |e_Y - (R - r)| = {worst:.2e} m (sag {sag:.1e})")
    assert worst <= sag + 1e-12
    np.testing.assert_allclose(wrap_angle(projection.heading_error + (angle + np.pi / 2)), 0.0,
                               atol=2e-3)
    np.testing.assert_allclose(projection.progress, radius * angle, atol=2e-3 * radius)


def test_heading_error_is_yaw_minus_tangent_wrapped() -> None:
    radius = 10.0
    path = circle_path(radius)
    angle = np.array([0.5, 1.5, 3.0])
    tangent = angle + np.pi / 2
    offsets = np.array([0.1, -0.2, 0.05])
    pose = np.column_stack([radius * np.cos(angle), radius * np.sin(angle),
                            wrap_angle(tangent + offsets + 2 * np.pi)])
    errors = path_errors(pose, path)
    e_y, heading = errors.lateral_error, errors.heading_error
    print("heading error", heading, "expected", offsets)
    np.testing.assert_allclose(heading, offsets, atol=2e-3)
    np.testing.assert_allclose(e_y, 0.0, atol=radius * (1 - np.cos(np.pi / 719 / 2)) + 1e-12)


def test_wrap_angle_range() -> None:
    wrapped = wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi + 0.1, -0.1]))
    np.testing.assert_allclose(wrapped, [-np.pi, -np.pi, -np.pi + 0.1, -0.1], atol=1e-12)


def test_error_stats_known_values() -> None:
    stats = ErrorStats.of(np.array([3.0, -4.0, 0.0, 1.0]))
    assert stats.max_abs == 4.0
    assert stats.mean_abs == 2.0
    assert stats.rmse == pytest.approx(np.sqrt(26.0 / 4.0))
    metrics = tracking_metrics(np.array([0.1, -0.3]), np.array([0.02, 0.01]))
    assert metrics.as_dict()["lateral_error_m"]["max_abs"] == pytest.approx(0.3)
    assert metrics.heading.mean_abs == pytest.approx(0.015)


def test_compute_time_stats() -> None:
    times = np.arange(1, 101, dtype=float) * 1e-3   # 1 .. 100 ms
    stats = ComputeTimeStats.of(times)
    assert stats.mean_s == pytest.approx(50.5e-3)
    assert stats.median_s == pytest.approx(50.5e-3)
    assert stats.p99_s == pytest.approx(np.percentile(times, 99))
    assert 99e-3 <= stats.p99_s <= 100e-3
    assert stats.max_s == 0.1 and stats.steps == 100


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: ErrorStats.of(np.array([])), "shape"),
        (lambda: ErrorStats.of(np.array([0.1, np.nan])), "non-finite"),
        (lambda: ComputeTimeStats.of(np.array([1e-3, -1e-3])), "negative"),
        (lambda: path_errors(np.array([[np.inf, 0.0, 0.0]]), straight_path()), "not finite"),
        (lambda: path_errors(np.zeros((4, 2)), straight_path()), "shape"),
    ],
)
def test_bad_inputs_raise_metrics_error(call, message: str) -> None:
    with pytest.raises(MetricsError, match=message):
        call()

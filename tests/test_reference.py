"""Reference paths: CSV loading and its errors, the double lane change, progress tracking."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controller.errors import PathError
from controller.reference import PathTracker, ReferencePath, lateral_error, read_path_csv


def hairpin(gap: float = 3.0, length: float = 30.0, spacing: float = 0.2) -> ReferencePath:
    """Out along +x, a half circle of diameter ``gap``, back along -x ``gap`` m higher."""
    straight = np.arange(0.0, length, spacing)
    turn = np.linspace(-math.pi / 2, math.pi / 2, int(math.pi * gap / 2 / spacing))[1:-1]
    x = np.concatenate((straight, length + gap / 2 * np.cos(turn), straight[::-1]))
    y = np.concatenate((np.zeros_like(straight), gap / 2 + gap / 2 * np.sin(turn), np.full_like(straight, gap)))
    yaw = np.concatenate((np.zeros_like(straight), turn + math.pi / 2, np.full_like(straight, math.pi)))
    return ReferencePath.from_arrays(x, y, yaw, name="hairpin")


def figure_loop(radius: float = 10.0, spacing: float = 0.2) -> ReferencePath:
    """A lemniscate-like loop that crosses itself at the origin."""
    t = np.linspace(0.0, 2 * math.pi, int(12 * radius / spacing))
    x, y = radius * np.sin(t), radius * np.sin(t) * np.cos(t)
    yaw = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    return ReferencePath.from_arrays(x, y, yaw, name="loop")


def test_double_lane_change_matches_its_formula() -> None:
    path = ReferencePath.double_lane_change()
    slope_yaw = np.arctan(np.gradient(path.y, path.x))
    error = np.max(np.abs(slope_yaw - path.yaw))
    print(f"length {path.length:.1f} m, Y range [{path.y.min():.3f}, {path.y.max():.3f}] m, "
          f"max |yaw - atan(dY/dX)| = {error:.2e} rad")
    assert error < 1e-3
    assert abs(path.y[0]) < 0.01 and path.y.max() == pytest.approx(3.53, abs=0.01)
    assert path.y[-1] == pytest.approx(4.05 - 5.7, abs=0.01)


def test_csv_round_trip(tmp_path) -> None:
    path = ReferencePath.double_lane_change(0.0, 100.0)
    file = tmp_path / "dlc.csv"
    path.to_csv(file)
    loaded = ReferencePath.from_csv(file)
    difference = max(np.max(np.abs(loaded.x - path.x)), np.max(np.abs(loaded.y - path.y)),
                     np.max(np.abs(loaded.yaw - path.yaw)))
    print(f"round trip max difference {difference:.2e}")
    assert difference < 1e-5


@pytest.mark.parametrize(("content", "message"), [
    ("", "empty file"),
    ("x,y,heading\n0,0,0\n0.1,0,0\n", "header must be 'x,y,yaw'"),
    ("x,y,yaw\n0,0,0\n", "at least 2 points"),
    ("x,y,yaw\n0,0,0\n0.1,0\n", "line 3 has 2 columns"),
    ("x,y,yaw\n0,0,0\n0.1,abc,0\n", "line 3 column y: not a number: 'abc'"),
    ("x,y,yaw\n0,0,0\n0.1,nan,0\n", "line 3: y = nan is not finite"),
    ("x,y,yaw\n0,0,0\n0.4,0,0\n1.0,0,0\n", "line 4: 0.600 m from the previous point"),
    ("x,y,yaw\n0,0,0\n0,0,0\n", "line 3: 0.000 m from the previous point"),
    ("x,y,yaw\n0,0,0\n0.005,0,0\n", "line 3: 0.005 m from the previous point"),
    # issue 17, defect 4: files that parsed but made no sense were followed
    ("x,y,yaw\n0,0,0\n0.25,0,1e300\n0.5,0,0\n", "line 3: yaw"),
    ("x,y,yaw\n0,0,3.14159\n0.25,0,3.14159\n0.5,0,3.14159\n", "line 2: yaw 3.1416 rad is 3.142 rad"),
    ("x,y,yaw\n1e7,0,0\n10000000.25,0,0\n", "line 2: x = 1e+07 m is outside the range of POS_X"),
    ("x,y,yaw\n0,0,0\n0.25,0,0\n0.5,0,3.1\n0.25,0.01,3.1\n", "line 4: the path turns by 3.1"),
])
def test_bad_csv_files_give_clear_errors(tmp_path, content: str, message: str) -> None:
    file = tmp_path / "bad.csv"
    file.write_text(content)
    with pytest.raises(PathError) as error:
        ReferencePath.from_csv(file)
    print(error.value)
    assert message in str(error.value) and "bad.csv" in str(error.value)


def test_yaw_is_wrapped_on_load_never_rejected_for_its_range(tmp_path) -> None:
    file = tmp_path / "wrapped.csv"
    two_pi = 2 * np.pi
    file.write_text(f"x,y,yaw\n0,0,{4 * two_pi}\n0.25,0,{-two_pi}\n0.5,0,0\n")
    points = read_path_csv(file)
    print("yaw as loaded:", points[:, 2])
    assert np.allclose(points[:, 2], 0.0, atol=1e-9)


def test_oversized_path_file_is_refused_while_reading(tmp_path) -> None:
    """Issue 17, defect 12: a 3-million-point file loaded with 885 MB. Now the reader stops
    at point 100,001 (the contract's limit), long before the file's end."""
    import tracemalloc
    file = tmp_path / "huge.csv"
    rows = "".join(f"{0.25 * i:.2f},0,0\n" for i in range(300_000))
    file.write_text("x,y,yaw\n" + rows)
    tracemalloc.start()
    with pytest.raises(PathError) as error:
        ReferencePath.from_csv(file)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(error.value, f"peak {peak / 1e6:.1f} MB")
    assert "line 100002: more than 100,000 points" in str(error.value)
    assert peak < 60e6


def test_missing_csv_file(tmp_path) -> None:
    with pytest.raises(PathError, match="path file not found"):
        ReferencePath.from_csv(tmp_path / "nope.csv")


def test_lateral_and_heading_error_signs() -> None:
    path = ReferencePath.double_lane_change(-10.0, 10.0)
    left = lateral_error(path, 0.0, 0.5, yaw=0.2)
    right = lateral_error(path, 0.0, -0.5, yaw=-0.2)
    print(left, right)
    assert left.lateral_error == pytest.approx(0.5, abs=0.01) and left.heading_error > 0
    assert right.lateral_error == pytest.approx(-0.5, abs=0.01) and right.heading_error < 0
    # Heading error is wrapped: yaw 2 pi + 0.1 is 0.1 off.
    assert lateral_error(path, 0.0, 0.0, yaw=2 * math.pi + 0.1).heading_error == pytest.approx(0.1, abs=0.01)


def test_tracker_does_not_jump_across_a_hairpin() -> None:
    path = hairpin(gap=3.0)
    tracker = PathTracker(path)
    # Drive the first leg 1.7 m to the left of it: closer to the return leg (1.3 m away).
    progresses = [tracker.update(x, 1.7 if x > 5 else 0.0, 0.0).progress for x in np.arange(0.0, 25.0, 0.3)]
    global_progress = lateral_error(path, 24.9, 1.7).progress
    print(f"tracker progress at x = 24.9: {progresses[-1]:.2f} m; global nearest: {global_progress:.2f} m")
    assert progresses[-1] == pytest.approx(24.9, abs=0.1)
    assert global_progress > path.length / 2  # the trap the tracker avoided
    assert np.all(np.diff(progresses) > 0)


def test_tracker_follows_a_self_crossing_loop() -> None:
    path = figure_loop()
    tracker = PathTracker(path)
    steps = np.diff([tracker.update(x, y, 0.0).progress for x, y in zip(path.x[::3], path.y[::3])])
    print(f"progress increments in [{steps.min():.3f}, {steps.max():.3f}] m over {steps.size} updates")
    assert np.all(steps > 0) and steps.max() < 1.0


def test_horizon_reference_spacing_and_yaw_continuity() -> None:
    path = hairpin(gap=3.0)
    tracker = PathTracker(path)
    tracker.update(20.0, 0.0, 0.0)
    reference = tracker.horizon_reference(tracker.progress, 10.0, 20, 0.025, 0.0)
    spacing = np.hypot(np.diff(reference[:, 0]), np.diff(reference[:, 1]))
    print(f"reference spacing {spacing.min():.4f}..{spacing.max():.4f} m (vx Ts = 0.25 m)")
    assert np.allclose(spacing, 0.25, atol=1e-6)
    # On the return leg the path yaw is pi; a vehicle yaw of -pi + 0.01 must see ~0 error.
    tracker.reset()
    projection = tracker.update(10.0, 3.0, -math.pi + 0.01)
    back = tracker.horizon_reference(projection.progress, 5.0, 10, 0.025, -math.pi + 0.01)
    print(f"heading error {projection.heading_error:.3f}, reference yaw {back[0, 2]:.3f}")
    assert abs(projection.heading_error) < 0.02
    assert abs(back[:, 2] - (-math.pi + 0.01)).max() < 0.02


def test_reference_beyond_the_end_continues_straight() -> None:
    path = ReferencePath.double_lane_change(0.0, 100.0)
    poses = path.pose_at(np.array([path.length + 10.0]))
    print(poses)
    assert poses[0, 0] == pytest.approx(110.0, abs=0.01) and poses[0, 1] == pytest.approx(path.y[-1], abs=0.01)


"""The identification drive (issue 20): the shipped circuit and scenario equal what
``python -m studies.identification drive`` writes, and they are what the docs say."""
from __future__ import annotations

import numpy as np

from controller.reference import read_path_csv
from hil.scenario import load_scenario
from studies.identification import (IDENTIFICATION_PATH_FILE, IDENTIFICATION_SCENARIO_FILE,
                                    speed_breakpoints, write_drive)


def test_shipped_drive_equals_the_regenerated_one(tmp_path):
    path, scenario = write_drive(tmp_path / "identification.csv", tmp_path / "drive.toml")
    assert path.read_text() == IDENTIFICATION_PATH_FILE.read_text()
    shipped = IDENTIFICATION_SCENARIO_FILE.read_text().replace("../../paths/", "")
    assert scenario.read_text().replace("../../paths/", "") == shipped


def test_drive_covers_3_to_30_mps_for_about_ten_minutes_on_a_path_long_enough():
    scenario = load_scenario(IDENTIFICATION_SCENARIO_FILE)
    times, speeds = speed_breakpoints()
    print(f"duration {scenario.duration_s} s, speeds {min(speeds)}-{max(speeds)} m/s")
    assert 540.0 <= scenario.duration_s <= 660.0 and (min(speeds), max(speeds)) == (3.0, 30.0)
    points = read_path_csv(scenario.path_file)  # the contract's path checks
    spacing = np.hypot(*np.diff(points[:, :2], axis=0).T)
    grid = np.arange(0.0, scenario.duration_s, 0.1)
    distance = np.trapezoid(np.interp(grid, times, speeds), grid)
    print(f"path {spacing.sum():.0f} m, drive {distance:.0f} m")
    assert spacing.sum() > distance + 200.0  # the MPC horizons stay on the path
    heading = np.unwrap(points[:, 2])
    curvature = np.diff(heading) / spacing
    radius = 1.0 / np.abs(curvature).max()
    print(f"tightest radius {radius:.0f} m: {30.0 ** 2 / radius:.1f} m/s^2 at 30 m/s")
    assert radius > 240.0 and curvature.min() < 0.0 < curvature.max()  # left and right bends
    assert np.allclose(points[0], [scenario.start.x_m, scenario.start.y_m, scenario.start.yaw_rad], atol=1e-6)


def test_laps_never_coincide_so_the_nearest_point_of_the_path_is_unambiguous():
    from scipy.spatial import cKDTree

    points = read_path_csv(IDENTIFICATION_PATH_FILE)
    arc = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(points[:, :2], axis=0).T))))
    tree = cKDTree(points[:, :2])
    closest_other_lap = np.inf
    for index in range(0, len(points), 50):
        near = tree.query_ball_point(points[index, :2], r=12.0)
        other = [j for j in near if abs(arc[j] - arc[index]) > 100.0]
        if other:
            closest_other_lap = min(closest_other_lap, float(np.min(
                np.hypot(*(points[other, :2] - points[index, :2]).T))))
    print(f"closest point of another lap: {closest_other_lap:.1f} m")
    assert closest_other_lap > 8.0  # |e_Y| stays far below half of it (the excitation stops at 1.5 m)

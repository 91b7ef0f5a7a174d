"""Identification of our plant from its own CAN logs (issue 20).

Part 1, the identification drive: a closed circuit driven for 10 minutes with speed steps
over 3-30 m/s (``hil/paths/identification.csv``, ``hil/scenarios/identification/drive.toml``),
written by ``python -m studies.identification drive``; a test checks that the shipped
files equal the regenerated ones.

The circuit is the polar curve r(theta) = R0 (1 + 0.2 sin 2 theta + 0.08 cos 3 theta),
R0 = 420 m: 2.78 km a lap, left and right bends, the tightest of radius 248 m (3.6 m/s^2
at 30 m/s, inside the grip of mu >= 0.5 with the excitation on top), laid out four times
in driving order (11.1 km, more than the 10-minute drive covers). The speed holds each of
20 levels for 22 s and ramps between them at 1.5 m/s^2; the levels visit 3-30 m/s in a
mixed order so that every speed is reached from below and from above.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from hil.path_files import PATH_DIR, write_path_csv
from hil.scenario import SCENARIO_DIR

IDENTIFICATION_PATH_FILE = PATH_DIR / "identification.csv"
#: In a folder of its own: the shipped scenarios of hil/scenarios/*.toml are the double
#: lane changes of the evaluation (tests/test_scenario.py).
IDENTIFICATION_SCENARIO_FILE = SCENARIO_DIR / "identification" / "drive.toml"
CIRCUIT_RADIUS_M = 420.0
CIRCUIT_SHAPE = (0.2, 0.08)  # amplitudes of sin 2 theta and cos 3 theta
CIRCUIT_LAPS = 4
POINT_SPACING_M = 0.45  # chords of 0.45 m of arc stay inside the contract's 0.5 m
#: Speed levels (m/s), each held for LEVEL_HOLD_S, ramps of SPEED_RAMP_MPS2 between them.
SPEED_LEVELS_MPS = (8.0, 15.0, 5.0, 22.0, 12.0, 28.0, 3.0, 18.0, 25.0, 10.0,
                    30.0, 6.0, 20.0, 14.0, 26.0, 4.0, 16.0, 24.0, 9.0, 12.0)
LEVEL_HOLD_S = 22.0
SPEED_RAMP_MPS2 = 1.5
DRIVE_MU = 0.85


def circuit_points(laps: int = CIRCUIT_LAPS, spacing_m: float = POINT_SPACING_M) -> np.ndarray:
    """The circuit, ``laps`` times in driving order (counter-clockwise), points
    ``spacing_m`` of arc apart: (n, 3) [x, y, yaw], starting at theta = 0 heading north."""
    a, b = CIRCUIT_SHAPE
    theta = np.linspace(0.0, 2.0 * math.pi, 400_001)
    radius = CIRCUIT_RADIUS_M * (1.0 + a * np.sin(2.0 * theta) + b * np.cos(3.0 * theta))
    x, y = radius * np.cos(theta), radius * np.sin(theta)
    arc = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    lap_length = arc[-1]
    s = np.arange(0.0, laps * lap_length, spacing_m)
    lap_s = np.mod(s, lap_length)
    theta_s = np.interp(lap_s, arc, theta)
    r = CIRCUIT_RADIUS_M * (1.0 + a * np.sin(2.0 * theta_s) + b * np.cos(3.0 * theta_s))
    dr = CIRCUIT_RADIUS_M * (2.0 * a * np.cos(2.0 * theta_s) - 3.0 * b * np.sin(3.0 * theta_s))
    px, py = r * np.cos(theta_s), r * np.sin(theta_s)
    tangent_x = dr * np.cos(theta_s) - r * np.sin(theta_s)
    tangent_y = dr * np.sin(theta_s) + r * np.cos(theta_s)
    yaw = np.arctan2(tangent_y, tangent_x)
    return np.column_stack([px - px[0], py - py[0], yaw])  # start at the origin


def speed_breakpoints() -> tuple[list[float], list[float]]:
    """Piecewise-linear target speed: (times s, speeds m/s) of the 10-minute drive."""
    times, speeds = [0.0], [SPEED_LEVELS_MPS[0]]
    for level in SPEED_LEVELS_MPS[1:]:
        hold_end = times[-1] + LEVEL_HOLD_S
        times.append(hold_end)
        speeds.append(speeds[-1])
        times.append(hold_end + abs(level - speeds[-1]) / SPEED_RAMP_MPS2)
        speeds.append(level)
    times.append(times[-1] + LEVEL_HOLD_S)
    speeds.append(speeds[-1])
    return times, speeds


def scenario_text(duration_s: float, start_yaw_rad: float) -> str:
    """The scenario TOML of the identification drive."""
    times, speeds = speed_breakpoints()
    kmh = [round(v * 3.6, 3) for v in speeds]
    return "\n".join([
        "# Identification drive (issue 20, docs/identification.md): the closed circuit of",
        "# studies/identification.py, 20 speed levels over 3-30 m/s held 22 s each with 1.5 m/s^2",
        "# ramps. Drive it with an excitation and record the bus, e.g.",
        "#   python -m hil run --scenario hil/scenarios/identification/drive.toml --controller lmpc \\",
        "#       --excite prbs-torque --log id.log",
        "# Written by `python -m studies.identification drive`; do not edit by hand.",
        'name = "identification"',
        f'description = "Identification drive: circuit, speed steps 3-30 m/s, {duration_s / 60:.0f} min, '
        f'mu = {DRIVE_MU}"',
        f"duration_s = {duration_s}",
        "",
        "[path]",
        "id = 1",
        'file = "../../paths/identification.csv"',
        "",
        "[road]",
        f"mu = {DRIVE_MU}",
        "",
        "[vehicle]",
        "mass_offset_kg = 0.0",
        "",
        "[start]",
        "x_m = 0.0",
        "y_m = 0.0",
        f"yaw_rad = {start_yaw_rad:.6f}",
        f"speed_kmh = {kmh[0]}",
        "",
        "[speed_profile]",
        f"time_s = {[round(t, 3) for t in times]}",
        f"target_speed_kmh = {kmh}",
        "",
    ])


def write_drive(path_file: Path = IDENTIFICATION_PATH_FILE,
                scenario_file: Path = IDENTIFICATION_SCENARIO_FILE) -> tuple[Path, Path]:
    """Write the circuit CSV and the scenario TOML (the shipped files by default)."""
    points = circuit_points()
    scenario_file.parent.mkdir(exist_ok=True)
    write_path_csv(path_file, points)
    times, _ = speed_breakpoints()
    scenario_file.write_text(scenario_text(round(times[-1], 3), float(points[0, 2])), encoding="ascii")
    return path_file, scenario_file


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``drive`` writes the identification drive's path and scenario."""
    parser = argparse.ArgumentParser(prog="python -m studies.identification", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("drive", help="write hil/paths/identification.csv and "
                                      "hil/scenarios/identification/drive.toml")
    args = parser.parse_args(argv)
    if args.command == "drive":
        for file in write_drive():
            print(f"wrote {file}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

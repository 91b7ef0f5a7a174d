"""The shipped reference path files: the double lane change written in the contract's CSV
format (header ``x,y,yaw``; metres, metres, radians; points at most 0.5 m apart, in driving
order), and the HIL's reader of path files.

The formula and the CSV format are `controller.reference`'s (`double_lane_change_curve`,
`read_path_csv`, `format_path_csv`): the ECU and the HIL read a path file with the same
code. Here their errors become `PathFileError`, the HIL's error for path files.

Regenerate the shipped path with ``python -m hil.path_files`` (writes ``hil/paths/dlc.csv``);
``tests/test_scenario.py`` checks that the shipped file equals the regenerated one.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from controller import reference
from controller.errors import PathError
from controller.reference import CSV_HEADER as PATH_CSV_HEADER
from controller.reference import MAX_POINT_SPACING_M
from controller.reference import double_lane_change_curve as double_lane_change
from hil.errors import PathFileError

__all__ = ["PATH_DIR", "DLC_PATH_FILE", "MAX_POINT_SPACING_M", "PATH_CSV_HEADER",
           "double_lane_change", "double_lane_change_points", "format_path_csv",
           "write_path_csv", "read_path_csv", "main"]

#: Folder of the shipped path CSVs.
PATH_DIR = Path(__file__).resolve().parent / "paths"
#: The double lane change used by every shipped scenario.
DLC_PATH_FILE = PATH_DIR / "dlc.csv"

# Shipped path extent: 20 m behind the start (X = 0) so a tracker that looks back has
# points, and 150 m ahead: the manoeuvre ends near X = 90 m, the rest shows settling and
# keeps the MPC horizons (<= ~15 m at 55 km/h) on the path until the scenarios end.
DLC_X_START_M = -20.0
DLC_X_END_M = 150.0
DLC_X_STEP_M = 0.25


def double_lane_change_points(
    x_start: float = DLC_X_START_M, x_end: float = DLC_X_END_M, x_step: float = DLC_X_STEP_M
) -> np.ndarray:
    """Sample the double lane change every ``x_step`` metres of X.

    Returns:
        Path points ``[x, y, yaw]``, shape (n, 3), in driving order (+X).
    """
    if not x_end > x_start:
        raise PathFileError(f"x_end = {x_end} must be greater than x_start = {x_start}")
    if not 0.0 < x_step <= MAX_POINT_SPACING_M:
        raise PathFileError(f"x_step = {x_step} must be in (0, {MAX_POINT_SPACING_M}] m")
    n_points = int(round((x_end - x_start) / x_step)) + 1
    x = x_start + x_step * np.arange(n_points)
    y, yaw = double_lane_change(x)
    return np.column_stack([x, y, yaw])


def format_path_csv(points: np.ndarray) -> str:
    """CSV text of path points (n, 3) with the contract header; 6 decimals (um, urad)."""
    try:
        return reference.format_path_csv(points)
    except PathError as e:
        raise PathFileError(str(e)) from e


def write_path_csv(file: Path, points: np.ndarray) -> None:
    """Write path points (n, 3) ``[x, y, yaw]`` to ``file`` in the contract's format."""
    Path(file).write_text(format_path_csv(points), encoding="ascii")


def read_path_csv(file: Path) -> np.ndarray:
    """Read and validate a contract path CSV with `controller.reference.read_path_csv`.

    Returns:
        Path points ``[x, y, yaw]``, shape (n, 3).

    Raises:
        PathFileError: the reader's `PathError`, same message (file, line or point, check).
    """
    try:
        return reference.read_path_csv(file)
    except PathError as e:
        raise PathFileError(str(e)) from e


def main(argv: list[str] | None = None) -> int:
    """CLI: regenerate the shipped double-lane-change CSV (or write it elsewhere)."""
    parser = argparse.ArgumentParser(prog="python -m hil.path_files", description=__doc__)
    parser.add_argument("--out", type=Path, default=DLC_PATH_FILE, help="CSV to write")
    args = parser.parse_args(argv)
    try:
        points = double_lane_change_points()
        write_path_csv(args.out, points)
    except (PathFileError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}: {len(points)} points, X {points[0, 0]:.1f} .. {points[-1, 0]:.1f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())

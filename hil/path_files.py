"""Reference path files: the double lane change of the architecture, written to and read
from the contract's CSV format (header ``x,y,yaw``; metres, metres, radians; points at most
0.5 m apart, in driving order).

Regenerate the shipped path with ``python -m hil.path_files`` (writes ``hil/paths/dlc.csv``);
``tests/test_scenario.py`` checks that the shipped file equals the regenerated one.
"""
from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

import numpy as np

from hil.errors import PathFileError

#: Folder of the shipped path CSVs.
PATH_DIR = Path(__file__).resolve().parent / "paths"
#: The double lane change used by every shipped scenario.
DLC_PATH_FILE = PATH_DIR / "dlc.csv"
#: Contract limit on the distance between consecutive points (m).
MAX_POINT_SPACING_M = 0.5
#: Header line required by the contract.
PATH_CSV_HEADER = ("x", "y", "yaw")

# Shipped path extent: 20 m behind the start (X = 0) so a tracker that looks back has
# points, and 150 m ahead: the manoeuvre ends near X = 90 m, the rest shows settling and
# keeps the MPC horizons (<= ~15 m at 55 km/h) on the path until the scenarios end.
DLC_X_START_M = -20.0
DLC_X_END_M = 150.0
DLC_X_STEP_M = 0.25


def double_lane_change(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The architecture's double lane change: lateral position and heading of X.

    Args:
        x: global X positions (m), shape (n,).

    Returns:
        ``(y, yaw)``: lateral position (m) and path heading (rad), each shape (n,).
    """
    x = np.asarray(x, dtype=float)
    z1 = 2.4 / 25.0 * (x - 27.19) - 1.2
    z2 = 2.4 / 21.95 * (x - 56.46) - 1.2
    y = 4.05 / 2.0 * (1.0 + np.tanh(z1)) - 5.7 / 2.0 * (1.0 + np.tanh(z2))
    # yaw = atan(dY/dX); sech^2 written as 1/cosh^2.
    slope = 4.05 / np.cosh(z1) ** 2 * (1.2 / 25.0) - 5.7 / np.cosh(z2) ** 2 * (1.2 / 21.95)
    return y, np.arctan(slope)


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
    points = _validated_points(np.asarray(points, dtype=float), "points")
    buffer = io.StringIO()
    buffer.write(",".join(PATH_CSV_HEADER) + "\n")
    for x, y, yaw in points:
        buffer.write(f"{x:.6f},{y:.6f},{yaw:.6f}\n")
    return buffer.getvalue()


def write_path_csv(file: Path, points: np.ndarray) -> None:
    """Write path points (n, 3) ``[x, y, yaw]`` to ``file`` in the contract's format."""
    Path(file).write_text(format_path_csv(points), encoding="ascii")


def read_path_csv(file: Path) -> np.ndarray:
    """Read and validate a contract path CSV.

    Returns:
        Path points ``[x, y, yaw]``, shape (n, 3).

    Raises:
        PathFileError: missing file, wrong header, non-numeric or non-finite values, fewer
            than two points, repeated points or points more than 0.5 m apart.
    """
    file = Path(file)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as e:
        raise PathFileError(f"{file}: cannot read path file: {e.strerror}") from e
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(cell.strip() for cell in rows[0]) != PATH_CSV_HEADER:
        found = ",".join(rows[0]) if rows else "<empty file>"
        raise PathFileError(f"{file}: header must be 'x,y,yaw', found '{found}'")
    values = []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != 3:
            raise PathFileError(f"{file}:{line_no}: expected 3 columns x,y,yaw, found {len(row)}")
        try:
            values.append([float(cell) for cell in row])
        except ValueError as e:
            raise PathFileError(f"{file}:{line_no}: not a number in {row}") from e
    return _validated_points(np.array(values, dtype=float).reshape(-1, 3), str(file))


def _validated_points(points: np.ndarray, where: str) -> np.ndarray:
    """Check shape, finiteness and spacing of path points (n, 3); return them unchanged."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise PathFileError(f"{where}: path points must have shape (n, 3), got {points.shape}")
    if points.shape[0] < 2:
        raise PathFileError(f"{where}: a path needs at least 2 points, got {points.shape[0]}")
    if not np.all(np.isfinite(points)):
        bad = int(np.argwhere(~np.isfinite(points))[0, 0])
        raise PathFileError(f"{where}: point {bad} is not finite: {points[bad].tolist()}")
    spacing = np.hypot(np.diff(points[:, 0]), np.diff(points[:, 1]))
    if np.any(spacing <= 0.0):
        bad = int(np.argmin(spacing))
        raise PathFileError(f"{where}: points {bad} and {bad + 1} coincide")
    if np.any(spacing > MAX_POINT_SPACING_M + 1e-9):
        bad = int(np.argmax(spacing))
        raise PathFileError(
            f"{where}: points {bad} and {bad + 1} are {spacing[bad]:.3f} m apart "
            f"(contract maximum {MAX_POINT_SPACING_M} m)"
        )
    return points


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

"""The shipped reference path files: the double lane change, a slalom and a
straight-curve-straight path, written in the contract's CSV format (header ``x,y,yaw``; metres, metres, radians; points at most 0.5 m
apart, in driving order), and the HIL's reader of path files.

The formula and the CSV format are `controller.reference`'s (`double_lane_change_curve`,
`read_path_csv`, `format_path_csv`): the ECU and the HIL read a path file with the same
code. Here their errors become `PathFileError`, the HIL's error for path files.

Regenerate the shipped paths with ``python -m hil.path_files`` (writes ``hil/paths/dlc.csv``)
and ``python -m hil.path_files --path slalom`` (``hil/paths/slalom.csv``, ``make
slalom-path``), ``python -m hil.path_files --path straight_curve``
(``hil/paths/straight_curve.csv``, the disturbance study's); ``tests/test_scenario.py``,
``tests/test_robustness_grid.py`` and ``tests/test_disturbance_study.py`` check that the
shipped files equal the regenerated ones.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controller import reference
from controller.errors import PathError
from controller.reference import CSV_HEADER as PATH_CSV_HEADER
from controller.reference import MAX_POINT_SPACING_M
from controller.reference import double_lane_change_curve as double_lane_change
from hil.errors import PathFileError

__all__ = ["PATH_DIR", "DLC_PATH_FILE", "SLALOM_PATH_FILE", "STRAIGHT_CURVE_PATH_FILE",
           "MAX_POINT_SPACING_M", "PATH_CSV_HEADER", "SlalomLayout", "SLALOM",
           "StraightCurveLayout", "STRAIGHT_CURVE", "double_lane_change",
           "double_lane_change_points", "slalom_curve", "slalom_points",
           "straight_curve_curvature", "straight_curve_points", "format_path_csv",
           "write_path_csv", "read_path_csv", "main"]

#: Folder of the shipped path CSVs.
PATH_DIR = Path(__file__).resolve().parent / "paths"
#: The double lane change used by every shipped scenario.
DLC_PATH_FILE = PATH_DIR / "dlc.csv"
#: The slalom of the robustness grid (``studies.robustness_grid``).
SLALOM_PATH_FILE = PATH_DIR / "slalom.csv"
#: The disturbance study's straight, curve, straight (``hil/scenarios/straight_curve.toml``).
STRAIGHT_CURVE_PATH_FILE = PATH_DIR / "straight_curve.csv"

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


@dataclass(frozen=True)
class SlalomLayout:
    """A slalom course: ``cone_count`` cones on the line Y = 0, ``cone_spacing_m`` apart from
    X = ``first_cone_x_m``; the path passes each cone ``offset_m`` to the side, left of the
    first, then alternately right and left. The path is sampled every ``x_step_m`` from
    ``x_start_m`` to ``x_end_m`` (m)."""

    first_cone_x_m: float = 40.0
    cone_spacing_m: float = 24.0
    cone_count: int = 6
    offset_m: float = 1.0
    x_start_m: float = -20.0
    x_end_m: float = 250.0
    x_step_m: float = 0.25

    @property
    def cone_x_m(self) -> np.ndarray:
        """X of the cones (m), shape (cone_count,)."""
        return self.first_cone_x_m + self.cone_spacing_m * np.arange(self.cone_count)

    @property
    def entry_x_m(self) -> float:
        """Where the path leaves the straight line Y = 0 (m): one spacing before the first cone."""
        return self.first_cone_x_m - self.cone_spacing_m

    @property
    def exit_x_m(self) -> float:
        """Where the path is back on Y = 0 (m): one spacing after the last cone."""
        return self.first_cone_x_m + self.cone_spacing_m * self.cone_count


#: The shipped slalom (``hil/paths/slalom.csv``): 6 cones 24 m apart from X = 40 m, passed
#: 1 m to the side, so the path is a sine of 48 m wavelength and 1 m amplitude between the
#: cones (curvature up to 0.0171 1/m: lateral acceleration 1.2 / 3.3 / 6.5 m/s^2 at
#: 30 / 50 / 70 km/h), up to 0.0224 1/m (1.6 / 4.3 / 8.5 m/s^2) on the swings into the
#: first and out of the last cone, where the envelope adds to the sine. The course is on
#: Y = 0 again at X = 184 m; the path runs straight to X = 250 m (settling, and room for
#: the MPC horizons).
SLALOM = SlalomLayout()


def _smoothstep(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quintic smoothstep 6u^5 - 15u^4 + 10u^3 on u clipped to [0, 1] and its derivative
    d/du: value, slope and curvature are 0 at u = 0 and at u = 1 (1 for the value)."""
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u ** 2), 30.0 * u ** 2 * (1.0 - u) ** 2


def slalom_curve(x: np.ndarray, layout: SlalomLayout = SLALOM) -> tuple[np.ndarray, np.ndarray]:
    """Lateral position and heading of the slalom path at X positions (m).

    Y = A w(X) cos(pi (X - X_1) / d), with A the cone offset, d the cone spacing and X_1
    the first cone: the cosine is +-A at every cone (left of the first, then alternately).
    The envelope w is 0 before X_1 - d, rises with a quintic smoothstep to 1 at X_1, is 1
    between the first and the last cone and falls back to 0 one spacing after the last,
    so the path leaves and rejoins the straight Y = 0 with continuous heading and
    curvature. yaw = atan(dY/dX) (the tangent, analytically).

    Args:
        x: global X positions (m), shape (n,).

    Returns:
        ``(y, yaw)`` in m and rad, each shape (n,).
    """
    x = np.asarray(x, dtype=float)
    d = layout.cone_spacing_m
    rise, rise_slope = _smoothstep((x - layout.entry_x_m) / d)
    fall, fall_slope = _smoothstep((layout.exit_x_m - x) / d)
    envelope = rise * fall
    envelope_slope = (rise_slope * fall - rise * fall_slope) / d
    phase = math.pi * (x - layout.first_cone_x_m) / d
    y = layout.offset_m * envelope * np.cos(phase)
    slope = layout.offset_m * (envelope_slope * np.cos(phase)
                               - envelope * np.sin(phase) * math.pi / d)
    return y, np.arctan(slope)


def slalom_points(layout: SlalomLayout = SLALOM) -> np.ndarray:
    """Sample :func:`slalom_curve` every ``layout.x_step_m`` of X over the layout's extent.

    Returns:
        Path points ``[x, y, yaw]``, shape (n, 3), in driving order (+X).
    """
    if layout.cone_count < 1 or not layout.cone_spacing_m > 0.0:
        raise PathFileError(f"slalom: needs >= 1 cone and a spacing > 0, got {layout}")
    if not (layout.x_start_m <= layout.entry_x_m and layout.exit_x_m <= layout.x_end_m):
        raise PathFileError(f"slalom: the course X {layout.entry_x_m} .. {layout.exit_x_m} m "
                            f"must lie within the path X {layout.x_start_m} .. {layout.x_end_m} m")
    if not 0.0 < layout.x_step_m <= MAX_POINT_SPACING_M / 1.5:
        raise PathFileError(f"slalom: x_step_m = {layout.x_step_m} must be in "
                            f"(0, {MAX_POINT_SPACING_M / 1.5:.3f}] m")
    n_points = int(round((layout.x_end_m - layout.x_start_m) / layout.x_step_m)) + 1
    x = layout.x_start_m + layout.x_step_m * np.arange(n_points)
    y, yaw = slalom_curve(x, layout)
    return np.column_stack([x, y, yaw])


@dataclass(frozen=True)
class StraightCurveLayout:
    """A straight, a left curve of constant radius between two clothoids, a straight.

    From arc length 0 (``lead_in_m`` behind the start X = 0, heading +X): ``lead_in_m`` +
    ``first_straight_m`` of straight, a clothoid of ``clothoid_m`` (curvature rising
    linearly from 0 to 1 / ``radius_m``), the arc, a clothoid back to 0, ``final_straight_m``
    of straight and ``margin_m`` more (beyond where a run ends: room for the MPC horizons).
    The whole curve turns by ``turn_deg``. Points every ``step_m`` of arc length (m, deg).
    """

    lead_in_m: float = 20.0
    first_straight_m: float = 60.0
    clothoid_m: float = 25.0
    radius_m: float = 50.0
    turn_deg: float = 90.0
    final_straight_m: float = 80.0
    margin_m: float = 30.0
    step_m: float = 0.25

    @property
    def arc_m(self) -> float:
        """Length of the constant-radius arc between the clothoids (m)."""
        return self.radius_m * (math.radians(self.turn_deg) - self.clothoid_m / self.radius_m)

    @property
    def curve_start_m(self) -> float:
        """Arc length where the first clothoid begins (m from the path's first point)."""
        return self.lead_in_m + self.first_straight_m

    @property
    def curve_end_m(self) -> float:
        """Arc length where the second clothoid ends and the final straight begins (m)."""
        return self.curve_start_m + 2.0 * self.clothoid_m + self.arc_m

    @property
    def run_end_m(self) -> float:
        """Arc length of the final straight's end, where a run stops (m)."""
        return self.curve_end_m + self.final_straight_m

    @property
    def length_m(self) -> float:
        """Whole path length (m)."""
        return self.run_end_m + self.margin_m


#: The shipped straight-curve-straight path (``hil/paths/straight_curve.csv``): 60 m of
#: straight from the start, 25 m clothoids into and out of a 50 m radius (3.9 m/s^2 at
#: 50 km/h), 90 degrees in all (the arc 53.5 m), then 80 m of straight and 30 m beyond.
STRAIGHT_CURVE = StraightCurveLayout()


def straight_curve_curvature(s: np.ndarray, layout: StraightCurveLayout = STRAIGHT_CURVE) -> np.ndarray:
    """Curvature (1/m) of the layout at arc lengths ``s`` (m), shape (n,) -> (n,)."""
    s = np.asarray(s, dtype=float)
    peak = 1.0 / layout.radius_m
    into = np.clip((s - layout.curve_start_m) / layout.clothoid_m, 0.0, 1.0)
    out_of = np.clip((layout.curve_end_m - s) / layout.clothoid_m, 0.0, 1.0)
    return peak * np.minimum(into, out_of)


def _straight_curve_heading(s: np.ndarray, layout: StraightCurveLayout) -> np.ndarray:
    """Heading (rad) at arc lengths ``s``: the curvature's integral, piecewise quadratic."""
    s = np.asarray(s, dtype=float)
    peak, c = 1.0 / layout.radius_m, layout.clothoid_m
    into = np.clip(s - layout.curve_start_m, 0.0, c)
    arc = np.clip(s - layout.curve_start_m - c, 0.0, layout.arc_m)
    out_of = np.clip(s - layout.curve_start_m - c - layout.arc_m, 0.0, c)
    return peak * (into ** 2 / (2.0 * c) + arc + out_of - out_of ** 2 / (2.0 * c))


def _cumulative_simpson(values: np.ndarray, h: float) -> np.ndarray:
    """Integral of samples ``values`` (2m + 1,) spaced ``h`` apart from the first sample to
    every second one, by Simpson's rule on each pair of steps: shape (m + 1,)."""
    pairs = (values[0:-1:2] + 4.0 * values[1::2] + values[2::2]) * h / 3.0
    return np.concatenate(([0.0], np.cumsum(pairs)))


def straight_curve_points(layout: StraightCurveLayout = STRAIGHT_CURVE) -> np.ndarray:
    """Sample the layout every ``layout.step_m`` of arc length, the start (arc length
    ``lead_in_m``) at the origin heading +X.

    The heading is exact; the positions are its cosine and sine integrated with Simpson's
    rule on 100 sub-steps per point (errors far below the file's micrometres).

    Returns:
        Path points ``[x, y, yaw]``, shape (n, 3), in driving order.
    """
    if not (layout.clothoid_m > 0.0 and layout.arc_m >= 0.0 and layout.radius_m > 0.0):
        raise PathFileError(f"straight_curve: the clothoids turn more than the curve: {layout}")
    if not 0.0 < layout.step_m <= MAX_POINT_SPACING_M / 1.5:
        raise PathFileError(f"straight_curve: step_m = {layout.step_m} must be in "
                            f"(0, {MAX_POINT_SPACING_M / 1.5:.3f}] m")
    n_points = int(round(layout.length_m / layout.step_m)) + 1
    fine = np.linspace(0.0, (n_points - 1) * layout.step_m, 200 * (n_points - 1) + 1)
    heading = _straight_curve_heading(fine, layout)
    x = _cumulative_simpson(np.cos(heading), fine[1] - fine[0])[::100]
    y = _cumulative_simpson(np.sin(heading), fine[1] - fine[0])[::100]
    s = layout.step_m * np.arange(n_points)
    start = int(round(layout.lead_in_m / layout.step_m))
    return np.column_stack([x - x[start], y - y[start], _straight_curve_heading(s, layout)])


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


#: ``--path`` choices: the generator and the shipped file of each path.
_SHIPPED_PATHS = {"dlc": (double_lane_change_points, DLC_PATH_FILE),
                  "slalom": (slalom_points, SLALOM_PATH_FILE),
                  "straight_curve": (straight_curve_points, STRAIGHT_CURVE_PATH_FILE)}


def main(argv: list[str] | None = None) -> int:
    """CLI: regenerate a shipped path CSV (or write it elsewhere)."""
    parser = argparse.ArgumentParser(prog="python -m hil.path_files", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--path", choices=sorted(_SHIPPED_PATHS), default="dlc",
                        help="which shipped path (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=None,
                        help="CSV to write (default: the shipped file, hil/paths/<path>.csv)")
    args = parser.parse_args(argv)
    generate, shipped = _SHIPPED_PATHS[args.path]
    args.out = args.out or shipped
    try:
        points = generate()
        write_path_csv(args.out, points)
    except (PathFileError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}: {len(points)} points, X {points[0, 0]:.1f} .. {points[-1, 0]:.1f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())

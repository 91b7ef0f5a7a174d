"""Reference paths and progress tracking along them.

``ReferencePath`` holds the planner's path as arrays (x, y, yaw unwrapped, arc length s);
``PathTracker`` follows the vehicle's progress along it without jumping to a far part of
the path that passes close by (hairpins, crossings), and produces the pose reference over
an MPC horizon plus the signed lateral and heading errors.

The path CSV format (``read_path_csv``, ``format_path_csv``) and the double-lane-change
formula (``double_lane_change_curve``) are implemented here only; ``hil.path_files`` and
the studies use them. Files are read and validated only when loaded
(``ReferencePath.from_csv``); nothing here raises at step time for finite inputs.

A path *file* passes the contract's checks (revision 2, "Reference path"; `check_path_file`)
before it is used: 2 to 100,000 points, finite values, inside the range of POS_X / POS_Y,
consecutive points 0.01 to 0.5 m apart, every yaw within 0.5 rad (modulo 2 pi) of the
direction to the next point, and no turn of more than 0.5 rad from one segment to the
next. The file is read row by row and refused at its 100,001st point, so a huge file
never fills the memory. Paths built in code (`ReferencePath.from_arrays`) get only the
basic checks of `check_path_points`.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controller.errors import PathError
from models.input_files import PATH_FILE_MAX_BYTES, bounded_lines, csv_number
from models.measurement import wrap_angle

#: Largest spacing allowed between consecutive path points (m).
MAX_POINT_SPACING_M = 0.5
#: Points closer than this count as duplicates (m): they would make the tangent undefined.
MIN_POINT_SPACING_M = 1e-6
#: Header line of a path CSV (``docs/can-contract.md``, "Reference path").
CSV_HEADER = ("x", "y", "yaw")
#: Path-file checks of the contract (revision 2, "Reference path").
MAX_PATH_POINTS = 100_000
MIN_FILE_POINT_SPACING_M = 0.01
MAX_YAW_DEVIATION_RAD = 0.5
MAX_SEGMENT_TURN_RAD = 0.5
#: Range of POS_X / POS_Y (24 bit signed, 0.001 m): a point outside cannot be driven to.
POSITION_MIN_M = -8388.608
POSITION_MAX_M = 8388.607


def double_lane_change_curve(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The double lane change of the architecture spec (Section IV of the paper).

    z1 = 2.4/25 (X - 27.19) - 1.2, z2 = 2.4/21.95 (X - 56.46) - 1.2,
    Y = 4.05/2 (1 + tanh z1) - 5.7/2 (1 + tanh z2),
    yaw = atan(dY/dX) = atan(4.05 sech^2(z1) 1.2/25 - 5.7 sech^2(z2) 1.2/21.95).

    Args:
        x: global X positions (m), shape (n,).

    Returns:
        ``(y, yaw)``: lateral position (m) and path heading (rad), each shape (n,).
    """
    x = np.asarray(x, dtype=float)
    z1 = 2.4 / 25.0 * (x - 27.19) - 1.2
    z2 = 2.4 / 21.95 * (x - 56.46) - 1.2
    y = 4.05 / 2.0 * (1.0 + np.tanh(z1)) - 5.7 / 2.0 * (1.0 + np.tanh(z2))
    yaw = np.arctan(4.05 / np.cosh(z1) ** 2 * (1.2 / 25.0)
                    - 5.7 / np.cosh(z2) ** 2 * (1.2 / 21.95))
    return y, yaw


def check_path_points(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, where: str) -> np.ndarray:
    """Validate path points and return the spacing between consecutive ones, shape (n - 1,).

    Checks: 1-D arrays of one length n >= 2, every value finite, consecutive points
    more than `MIN_POINT_SPACING_M` and at most `MAX_POINT_SPACING_M` apart.

    Raises:
        PathError: naming ``where``, the point(s) and the check that failed.
    """
    arrays = [np.asarray(a, dtype=float) for a in (x, y, yaw)]
    if any(a.ndim != 1 for a in arrays) or len({a.size for a in arrays}) != 1:
        raise PathError(f"{where}: x, y, yaw must be 1-D arrays of equal length, got shapes "
                        f"{[a.shape for a in arrays]}")
    if arrays[0].size < 2:
        raise PathError(f"{where}: needs at least 2 points, got {arrays[0].size}")
    for label, values in zip(CSV_HEADER, arrays):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise PathError(f"{where}: point {bad[0]} has non-finite {label} = {values[bad[0]]}")
    spacing = np.hypot(np.diff(arrays[0]), np.diff(arrays[1]))
    too_far = np.flatnonzero(spacing > MAX_POINT_SPACING_M)
    if too_far.size:
        i = too_far[0]
        raise PathError(f"{where}: points {i} and {i + 1} are {spacing[i]:.3f} m apart "
                        f"(at most {MAX_POINT_SPACING_M} m allowed)")
    duplicate = np.flatnonzero(spacing < MIN_POINT_SPACING_M)
    if duplicate.size:
        i = duplicate[0]
        raise PathError(f"{where}: points {i} and {i + 1} coincide")
    return spacing


def _parse_path_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The numbers of a path CSV and their line numbers, shapes (n, 3) and (n,); header
    and cells checked, not the points. Read row by row: more than `MAX_PATH_POINTS`
    points is refused at the first one too many, before the rest is read."""
    values: list[tuple[float, ...]] = []
    lines: list[int] = []
    header: tuple[str, ...] | None = None
    try:
        # every line bounded as it is read (models/input_files.py), as in the C ECU
        reader = csv.reader(bounded_lines(path, PATH_FILE_MAX_BYTES, PathError))
        for row in reader:
            line = reader.line_num
            if not row or not any(cell.strip() for cell in row):
                continue
            if header is None:
                header = tuple(cell.strip() for cell in row)
                if header != CSV_HEADER:
                    raise PathError(f"{path}: line {line}: header must be 'x,y,yaw', "
                                    f"got {','.join(header)!r}")
                continue
            if len(values) == MAX_PATH_POINTS:
                raise PathError(f"{path}: line {line}: more than {MAX_PATH_POINTS:,} "
                                "points (the contract's limit)")
            if len(row) != 3:
                raise PathError(f"{path}: line {line} has {len(row)} columns, expected 3")
            point = []
            for j, cell in enumerate(row):
                try:
                    point.append(csv_number(cell))
                except ValueError as e:
                    raise PathError(f"{path}: line {line} column {CSV_HEADER[j]}: "
                                    f"not a number: {cell!r}") from e
            values.append(tuple(point))
            lines.append(line)
    except FileNotFoundError as e:
        raise PathError(f"{path}: path file not found") from e
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise PathError(f"{path}: cannot read path file: {e}") from e
    if header is None:
        raise PathError(f"{path}: empty file (expected header 'x,y,yaw')")
    return np.array(values, dtype=float).reshape(-1, 3), np.array(lines, dtype=int)


def _angle_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| modulo 2 pi, in [0, pi]."""
    return np.abs(np.mod(np.asarray(a) - np.asarray(b) + math.pi, 2.0 * math.pi) - math.pi)


def check_path_file(points: np.ndarray, lines: np.ndarray, where: str) -> np.ndarray:
    """The contract's checks of a path file (revision 2, "Reference path").

    Args:
        points: ``[x, y, yaw]`` rows as read, shape (n, 3).
        lines: the file line of each point, shape (n,) (for the message).
        where: the file name.

    Returns:
        The points with yaw wrapped to [-pi, pi), shape (n, 3).

    Raises:
        PathError: naming the file, the line and the check that failed.
    """
    n = points.shape[0]
    if n < 2:
        raise PathError(f"{where}: needs at least 2 points, got {n}")
    if n > MAX_PATH_POINTS:
        raise PathError(f"{where}: line {lines[MAX_PATH_POINTS]}: more than "
                        f"{MAX_PATH_POINTS:,} points (the contract's limit)")
    bad = np.argwhere(~np.isfinite(points))
    if bad.size:
        i, j = bad[0]
        raise PathError(f"{where}: line {lines[i]}: {CSV_HEADER[j]} = {points[i, j]} is not finite")
    xy = points[:, :2]
    outside = np.argwhere((xy < POSITION_MIN_M) | (xy > POSITION_MAX_M))
    if outside.size:
        i, j = outside[0]
        raise PathError(f"{where}: line {lines[i]}: {CSV_HEADER[j]} = {xy[i, j]:g} m is outside "
                        f"the range of POS_X / POS_Y [{POSITION_MIN_M}, {POSITION_MAX_M}] m")
    step = np.diff(xy, axis=0)
    spacing = np.hypot(step[:, 0], step[:, 1])
    off = np.flatnonzero((spacing < MIN_FILE_POINT_SPACING_M) | (spacing > MAX_POINT_SPACING_M))
    if off.size:
        i = off[0]
        raise PathError(f"{where}: line {lines[i + 1]}: {spacing[i]:.3f} m from the previous "
                        f"point (must be {MIN_FILE_POINT_SPACING_M} to {MAX_POINT_SPACING_M} m)")
    direction = np.arctan2(step[:, 1], step[:, 0])           # segment i: point i -> i + 1
    yaw = points[:, 2]
    point_direction = np.concatenate((direction, direction[-1:]))
    deviation = _angle_difference(yaw, point_direction)
    off = np.flatnonzero(deviation > MAX_YAW_DEVIATION_RAD)
    if off.size:
        i = off[0]
        raise PathError(f"{where}: line {lines[i]}: yaw {yaw[i]:.4f} rad is {deviation[i]:.3f} "
                        f"rad from the direction of the points ({point_direction[i]:.4f} rad; "
                        f"at most {MAX_YAW_DEVIATION_RAD} rad)")
    turn = _angle_difference(direction[1:], direction[:-1])
    off = np.flatnonzero(turn > MAX_SEGMENT_TURN_RAD)
    if off.size:
        i = off[0]
        raise PathError(f"{where}: line {lines[i + 1]}: the path turns by {turn[i]:.3f} rad at "
                        f"this point (at most {MAX_SEGMENT_TURN_RAD} rad; no doubling back)")
    checked = points.copy()
    checked[:, 2] = wrap_angle(yaw)
    return checked


def read_path_csv(path: str | Path) -> np.ndarray:
    """Read and validate a path CSV (header ``x,y,yaw``; m, m, rad; one point per row).

    Returns:
        Path points ``[x, y, yaw]``, yaw wrapped to [-pi, pi) (not unwrapped), shape (n, 3).

    Raises:
        PathError: missing or unreadable file, wrong header, a row that is not three
            numbers, or points that fail `check_path_file`; the message names the file
            and the line.
    """
    path = Path(path)
    points, lines = _parse_path_csv(path)
    return check_path_file(points, lines, str(path))


def format_path_csv(points: np.ndarray, yaw_decimals: int = 6) -> str:
    """CSV text that `read_path_csv` reads: the header, then one row ``x,y,yaw`` per point.

    Args:
        points: ``[x, y, yaw]`` rows, shape (n, 3); checked with `check_path_points`.
        yaw_decimals: decimals of yaw (x and y get 6: micrometres).
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PathError(f"path points must have shape (n, 3), got {points.shape}")
    check_path_points(points[:, 0], points[:, 1], points[:, 2], "path points")
    rows = [",".join(CSV_HEADER)]
    rows.extend(f"{x:.6f},{y:.6f},{yaw:.{yaw_decimals}f}" for x, y, yaw in points)
    return "\n".join(rows) + "\n"


@dataclass(frozen=True, eq=False)
class ReferencePath:
    """A planar path: arrays of shape (n,) with x, y (m), yaw (rad, unwrapped) and s (m).

    ``s`` is the cumulative chord length, starting at 0. Build with ``from_arrays``,
    ``from_csv`` or ``double_lane_change``; they validate the points.
    """

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    s: np.ndarray
    name: str = ""

    @classmethod
    def from_arrays(cls, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, name: str = "") -> "ReferencePath":
        """Validate points (each shape (n,), n >= 2, finite, 0 < spacing <= 0.5 m)."""
        spacing = check_path_points(x, y, yaw, name or "path")
        s = np.concatenate(([0.0], np.cumsum(spacing)))
        # Unwrapped so interpolation between points never sweeps through +-pi.
        arrays = [np.array(x, dtype=float), np.array(y, dtype=float),
                  np.unwrap(np.asarray(yaw, dtype=float)), s]
        for array in arrays:
            array.setflags(write=False)  # a path is shared by tracker and metrics: read-only
        return cls(*arrays, name)

    @classmethod
    def from_csv(cls, path: str | Path) -> "ReferencePath":
        """Load a CSV with header ``x,y,yaw`` (m, m, rad), one point per row, that passes
        the contract's checks (`read_path_csv`)."""
        points = read_path_csv(path)
        return cls.from_arrays(points[:, 0], points[:, 1], points[:, 2], name=str(path))

    @classmethod
    def double_lane_change(cls, x_start: float = -20.0, x_end: float = 180.0,
                           spacing: float = 0.25) -> "ReferencePath":
        """`double_lane_change_curve` sampled every ``spacing`` m in X from ``x_start`` to
        ``x_end``."""
        if not (0.0 < spacing <= MAX_POINT_SPACING_M / 1.5):
            raise PathError(f"double_lane_change: spacing must be in (0, {MAX_POINT_SPACING_M / 1.5:.3f}] m, got {spacing}")
        if not x_end > x_start:
            raise PathError(f"double_lane_change: x_end ({x_end}) must be > x_start ({x_start})")
        x = np.arange(x_start, x_end + 0.5 * spacing, spacing)
        y, yaw = double_lane_change_curve(x)
        return cls.from_arrays(x, y, yaw, name="double_lane_change")

    def to_csv(self, path: str | Path, yaw_decimals: int = 8) -> None:
        """Write the CSV that ``from_csv`` reads (yaw wrapped to [-pi, pi))."""
        points = np.column_stack([self.x, self.y, wrap_angle(np.asarray(self.yaw))])
        Path(path).write_text(format_path_csv(points, yaw_decimals), encoding="ascii")

    @property
    def length(self) -> float:
        """Total arc length (m)."""
        return float(self.s[-1])

    def pose_at(self, s: np.ndarray) -> np.ndarray:
        """Interpolated pose [x, y, yaw (unwrapped)] at arc lengths ``s`` (k,) -> (k, 3).

        Beyond either end the path continues straight along its end tangent.
        """
        s = np.asarray(s, dtype=float)
        out = np.empty(s.shape + (3,))
        out[..., 0] = np.interp(s, self.s, self.x)
        out[..., 1] = np.interp(s, self.s, self.y)
        out[..., 2] = np.interp(s, self.s, self.yaw)
        for mask, index, base in ((s > self.s[-1], -1, self.s[-1]), (s < 0.0, 0, 0.0)):
            if np.any(mask):
                extra = s[mask] - base
                heading = self.yaw[index]
                out[mask, 0] = self.x[index] + extra * math.cos(heading)
                out[mask, 1] = self.y[index] + extra * math.sin(heading)
        return out


@dataclass(frozen=True)
class PathProjection:
    """The vehicle's foot point on the path.

    ``progress`` (m of arc length), ``lateral_error`` (m, positive = vehicle left of the
    path), ``heading_error`` (rad, vehicle yaw minus path yaw, wrapped), ``path_yaw``
    (rad, unwrapped path yaw at the foot point).
    """

    progress: float
    lateral_error: float
    heading_error: float
    path_yaw: float


def _project(path: ReferencePath, x: float, y: float, first: int, last: int) -> tuple[float, float, int]:
    """Nearest foot point on segments ``first .. last - 1``: (progress, signed distance, segment)."""
    x0, y0 = path.x[first:last], path.y[first:last]
    dx, dy = path.x[first + 1:last + 1] - x0, path.y[first + 1:last + 1] - y0
    length_sq = dx * dx + dy * dy
    t = np.clip(((x - x0) * dx + (y - y0) * dy) / length_sq, 0.0, 1.0)
    ex, ey = x - (x0 + t * dx), y - (y0 + t * dy)
    k = int(np.argmin(ex * ex + ey * ey))
    seg_len = math.sqrt(length_sq[k])
    # Cross product of the tangent with the offset: > 0 when the point is to the left.
    signed = (dx[k] * ey[k] - dy[k] * ex[k]) / seg_len
    return float(path.s[first + k] + t[k] * seg_len), float(signed), first + k


def _projection_result(path: ReferencePath, x: float, y: float, yaw: float, first: int,
                       last: int) -> PathProjection:
    progress, signed, _ = _project(path, x, y, first, last)
    path_yaw = float(np.interp(progress, path.s, path.yaw))
    return PathProjection(progress, signed, float(wrap_angle(yaw - path_yaw)), path_yaw)


def lateral_error(path: ReferencePath, x: float, y: float, yaw: float = 0.0) -> PathProjection:
    """Foot point by a search over the WHOLE path (nearest segment).

    For metrics on paths that never come back near themselves; a controller uses
    ``PathTracker``, whose windowed search cannot jump.
    """
    return _projection_result(path, x, y, yaw, 0, path.x.size - 1)


class PathTracker:
    """Progress along a path, searched only in a window around the last progress.

    The first ``update`` (after construction or ``reset``) searches the whole path; later
    ones only the segments within ``window_behind_m`` behind and ``window_ahead_m`` ahead of
    the last progress, so a part of the path that comes back close (hairpin, crossing) is
    never picked while the vehicle follows the path.
    """

    def __init__(self, path: ReferencePath, window_ahead_m: float = 6.0, window_behind_m: float = 2.0) -> None:
        if not (window_ahead_m > 0.0 and window_behind_m >= 0.0):
            raise PathError(f"window_ahead_m ({window_ahead_m}) must be > 0 and window_behind_m "
                            f"({window_behind_m}) >= 0")
        self.path = path
        self._ahead = window_ahead_m
        self._behind = window_behind_m
        self._progress: float | None = None

    @property
    def progress(self) -> float | None:
        """Last progress along the path (m), None before the first update."""
        return self._progress

    def reset(self) -> None:
        """Forget the progress; the next update searches the whole path."""
        self._progress = None

    def update(self, x: float, y: float, yaw: float) -> PathProjection:
        """Project the vehicle position (m) onto the path and advance the progress."""
        n_segments = self.path.x.size - 1
        if self._progress is None:
            first, last = 0, n_segments
        else:
            s = self.path.s
            first = max(int(np.searchsorted(s, self._progress - self._behind, side="right")) - 1, 0)
            last = min(int(np.searchsorted(s, self._progress + self._ahead, side="left")) + 1, n_segments)
            last = max(last, first + 1)
        result = _projection_result(self.path, x, y, yaw, first, last)
        self._progress = result.progress
        return result

    def horizon_reference(self, progress: float, vx: float, n_steps: int, ts: float,
                          vehicle_yaw: float) -> np.ndarray:
        """Pose reference over the horizon, shape (n_steps, 3): [x, y, yaw] at steps 1..n_steps.

        s_i = progress + vx * ts * i (vx clipped at 0: no reference behind the vehicle).
        The yaw is shifted by a multiple of 2 pi so that it is continuous with the vehicle's
        (wrapped) yaw: the yaw error never sees a 2 pi jump.
        """
        steps = np.arange(1, n_steps + 1)
        reference = self.path.pose_at(progress + max(vx, 0.0) * ts * steps)
        first_yaw = reference[0, 2]
        reference[:, 2] -= 2.0 * math.pi * round((first_yaw - vehicle_yaw) / (2.0 * math.pi))
        return reference

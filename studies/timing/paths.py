"""A reference path long enough for minutes of driving: repeated double lane changes.

The paper's double lane change (`ReferencePath.double_lane_change`, X = -20..150 m) ends
1.65 m to the right of where it starts. Segment k of the long path is that manoeuvre
shifted by 170 k m in X, mirrored on every second segment (Y -> -1.65 - Y, yaw -> -yaw)
so that it returns to the start lane: the joints are continuous to 0.1 mm and the
controllers steer through a lane change every 85 m, as in the paper's manoeuvre, for the
whole run.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: X range of one double lane change segment, m (Y is 0 / -1.65 m flat at the ends).
SEGMENT_START_M = -20.0
SEGMENT_END_M = 150.0
#: Lateral offset at the end of one manoeuvre, m.
SEGMENT_OFFSET_M = -1.65
SPACING_M = 0.25


def repeated_lane_change(length_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, yaw (each (n,)) of alternating double lane changes covering ``length_m``.

    Raises:
        ValueError: ``length_m`` not positive and finite.
    """
    from controller.reference import ReferencePath

    if not (math.isfinite(length_m) and length_m > 0):
        raise ValueError(f"path length must be a positive finite number of metres, got {length_m!r}")
    one = ReferencePath.double_lane_change(SEGMENT_START_M, SEGMENT_END_M, SPACING_M)
    # the last point is left out: the next segment starts there
    x0, y0, yaw0 = (np.asarray(values)[:-1] for values in (one.x, one.y, one.yaw))
    segment_length = SEGMENT_END_M - SEGMENT_START_M
    n_segments = int(math.ceil(length_m / segment_length)) + 1
    xs, ys, yaws = [], [], []
    for k in range(n_segments):
        mirrored = k % 2 == 1
        xs.append(x0 + k * segment_length)
        ys.append(SEGMENT_OFFSET_M - y0 if mirrored else y0)
        yaws.append(-yaw0 if mirrored else yaw0)
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(yaws)


def write_repeated_lane_change(file: Path, length_m: float) -> Path:
    """Write the path (CSV ``x,y,yaw``, as the ECU's ``--path`` reads it) to ``file``."""
    from controller.reference import ReferencePath

    x, y, yaw = repeated_lane_change(length_m)
    file.parent.mkdir(parents=True, exist_ok=True)
    ReferencePath.from_arrays(x, y, yaw, name="repeated_lane_change").to_csv(file)
    return file

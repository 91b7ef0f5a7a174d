"""Steady lateral offsets on a path's straight sections, from a run's e_Y trace (the
disturbance study, ``make disturbances``; docs/disturbances.md).

A straight section is a stretch of the reference path whose curvature stays below
:data:`STRAIGHT_CURVATURE` (1e-4 1/m: a radius of 10 km, 0.02 m/s^2 at 50 km/h) for at
least :data:`MIN_STRAIGHT_M`. A run's steady offset on a section is the mean signed e_Y
(m, left of the path positive) over the last :data:`WINDOW_S` seconds the car spent on
it, where it spent at least :data:`MIN_TIME_ON_S` there (the rest, at least one second,
lets the transients of the start or of the curve before it settle); none otherwise.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: Curvature (1/m) below which the path counts as straight.
STRAIGHT_CURVATURE = 1e-4
#: Shortest straight section (m of arc length).
MIN_STRAIGHT_M = 10.0
#: The steady window at the end of the car's time on a straight (s).
WINDOW_S = 2.0
#: Least time on a straight for a steady offset (s): the window plus 1 s of settling.
MIN_TIME_ON_S = 3.0


@dataclass(frozen=True)
class Straight:
    """A straight section of a path: arc lengths ``start_m`` to ``end_m`` (m) and its name
    in the tables ("first straight", "final straight", or "straight N")."""

    start_m: float
    end_m: float
    label: str


def straight_sections(s: np.ndarray, yaw: np.ndarray) -> list[tuple[float, float]]:
    """Arc-length ranges (m) of the straight sections of a path given by its points' arc
    length ``s`` (n,) and unwrapped heading ``yaw`` (n,) (``ReferencePath.s``, ``.yaw``)."""
    curvature = np.abs(np.gradient(np.asarray(yaw, dtype=float), np.asarray(s, dtype=float)))
    straight = np.concatenate(([False], curvature < STRAIGHT_CURVATURE, [False]))
    edges = np.flatnonzero(np.diff(straight.astype(np.int8)))
    ranges = [(float(s[first]), float(s[last - 1])) for first, last in zip(edges[0::2], edges[1::2])]
    return [(a, b) for a, b in ranges if b - a >= MIN_STRAIGHT_M]


def steady_offset(trace: Mapping[str, Sequence[float]], start_m: float, end_m: float) -> float | None:
    """Mean e_Y (m) over the last :data:`WINDOW_S` of the car's time on the straight from
    ``start_m`` to ``end_m``, or None when it spent less than :data:`MIN_TIME_ON_S` there.

    Args:
        trace: ``time_s``, ``e_y`` and ``progress`` (the foot point's arc length, m), equal
            lengths (``studies.campaign.cell``'s ``trace``).
    """
    time = np.asarray(trace["time_s"], dtype=float)
    e_y = np.asarray(trace["e_y"], dtype=float)
    progress = np.asarray(trace["progress"], dtype=float)
    on = (progress >= start_m) & (progress <= end_m)
    if not np.any(on):
        return None
    first, last = time[on].min(), time[on].max()
    if last - first < MIN_TIME_ON_S - 1e-9:
        return None
    window = on & (time >= last - WINDOW_S - 1e-9)
    return float(np.mean(e_y[window]))


def label_straights(ranges: Sequence[tuple[float, float]], reached: Sequence[bool]) -> list[Straight]:
    """Name the sections that some run ``reached`` (had a steady offset on): the last one
    "final straight", a first one before it "first straight", others "straight N"."""
    kept = [r for r, hit in zip(ranges, reached) if hit]
    names = []
    for i, (start, end) in enumerate(kept):
        name = ("final straight" if i == len(kept) - 1 else
                "first straight" if i == 0 else f"straight {i + 1}")
        names.append(Straight(start, end, name))
    return names

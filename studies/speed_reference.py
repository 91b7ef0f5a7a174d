"""A figure of the machine's speed, to set beside the timings of a results file.

A virtual machine's CPU model often says only "AMD EPYC", while the host behind it can be
twice as fast on one day as on another: every step figure of ``make bench``, the solvers'
own times included, doubled between two runs of 2026-12-05, and the older code measured on
the newer machine gave the newer figures (0.050 / 0.070 ms against 0.049 / 0.068 ms for the
C ESO-DKMPC step, p50 / p99: `python -m studies.bench --controllers eso-dkmpc,lmpc --no-ecu`
in a worktree of 49ecf84 and in the newer tree, side by side, after `make firmware` in each).
`speed_reference` times a fixed workload, so that two results files say whether their
machines were alike.
"""
from __future__ import annotations

import time

#: Repeats of the reference workload; the fastest counts (the least disturbed).
SPEED_REFERENCE_REPEATS = 7


def _reference_workload() -> float:
    """What a Python control step is made of: a Python loop over floats and small numpy
    operations (a 30 x 30 product, a cumulative sum, element-wise maths); returns a sum so
    that nothing is optimised away."""
    import numpy as np

    total = 0.0
    for k in range(20000):
        total += (k % 7) * 0.5
    matrix = np.linspace(0.0, 1.0, 900).reshape(30, 30)
    vector = np.ones(30)
    for _ in range(400):
        vector = np.cos(matrix @ vector)
        total += float(np.cumsum(vector)[-1])
    return total


def speed_reference() -> float:
    """The fastest of `SPEED_REFERENCE_REPEATS` runs of a fixed workload, ms: a figure of
    the machine's speed for one core, to set beside the timings of a results file."""
    best = float("inf")
    for _ in range(SPEED_REFERENCE_REPEATS):
        started = time.perf_counter()
        _reference_workload()
        best = min(best, time.perf_counter() - started)
    return best * 1e3

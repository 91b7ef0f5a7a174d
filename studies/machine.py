"""The machine a study or benchmark ran on, for the headers of results files.

Wall-clock figures depend on the CPU and on what else the machine was doing: every table
with times names the CPU model, the number of logical CPUs and the Python version, and
the benchmark also the load average when it started.

A virtual machine's CPU model often says only "AMD EPYC", while the host behind it can be
twice as fast on one day as on another (every step figure of ``make bench``, the solvers'
own times included, doubled between two runs of 2026-12-05 without a change to the solver
code). `speed_reference` times a fixed workload, so that two results files say whether
their machines were alike.
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path

#: Repeats of the reference workload; the fastest counts (the least disturbed).
SPEED_REFERENCE_REPEATS = 7


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (Linux), else ``platform``'s answer."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass  # not Linux: keep platform's answer
    return platform.processor() or platform.machine()


def machine_description() -> str:
    """CPU model, logical CPU count and Python version: ``"<cpu>, 2 logical CPUs, Python 3.11.7"``."""
    return f"{cpu_model()}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}"


def load_average() -> tuple[float, float, float]:
    """The 1, 5 and 15 minute load averages (NaN where the OS does not report them)."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return float("nan"), float("nan"), float("nan")
    return one, five, fifteen


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

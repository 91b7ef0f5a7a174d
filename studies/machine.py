"""The machine a study or benchmark ran on, for the headers of results files.

Wall-clock figures depend on the CPU and on what else the machine was doing: every table
with times names the CPU model, the number of logical CPUs and the Python version, and
the benchmark also the load average when it started.
"""
from __future__ import annotations

import os
import platform
from pathlib import Path


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

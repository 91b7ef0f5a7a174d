"""What a study commits and what it leaves to the machine: the summary keys whose values the
host decides (wall and step times, overruns), split from those the inputs decide, so that a
rerun of the same code writes the same committed bytes (make run, tables, identify,
vehicle-variants put the machine's part under results/logs/).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

#: Summary keys whose values depend on the machine and its load, not on the run's inputs:
#: they go to a timing file under results/logs/ (not under version control), so the
#: committed metrics stay the same from one machine to the next and a rerun of the same
#: code leaves the checkout clean.
MACHINE_KEYS = ("wall_time_s", "seconds", "compute_time", "solver_time_mean_s", "solve_time_us_median",
                "solve_time_us_max", "ecu_overruns", "realtime_overruns")


def split_machine_keys(runs: Sequence[Mapping[str, Any]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Each run's summary in two: the part its inputs decide, and the part that depends on
    the machine (:data:`MACHINE_KEYS`, with the run's scenario and controller to name it)."""
    inputs_only = [{k: v for k, v in run.items() if k not in MACHINE_KEYS} for run in runs]
    machine = [{"scenario": run["scenario"], "controller": run["controller"],
                **{k: run[k] for k in MACHINE_KEYS if k in run}} for run in runs]
    return inputs_only, machine

"""``make run`` writes the same tracked bytes on every rerun: the machine-dependent part of
each run's summary goes beside the frame logs (studies/run_all.py, docs/run.md)."""
from __future__ import annotations

import json
from pathlib import Path

from studies import run_all
from studies.machine_figures import MACHINE_KEYS, split_machine_keys


def _run(out: Path) -> None:
    assert run_all.main(["--controllers", "lmpc", "--scenarios", "dlc_high_mu", "--duration", "0.5",
                         "--out", str(out), "--logs", str(out / "logs")]) == 0


def test_run_metrics_hold_no_machine_figures_and_repeat_exactly(tmp_path: Path) -> None:
    _run(tmp_path)
    first = (tmp_path / "run_metrics.json").read_bytes()
    _run(tmp_path)  # the same folder again, as make run does with results/
    assert first == (tmp_path / "run_metrics.json").read_bytes()
    [run] = json.loads(first)["runs"]
    assert run["completed"] and run["controller"] == "lmpc"
    assert not set(run) & set(MACHINE_KEYS)
    [timing] = json.loads((tmp_path / "logs" / "run_timing.json").read_text())["runs"]
    assert (timing["scenario"], timing["controller"]) == ("dlc_high_mu", "lmpc")
    assert timing["wall_time_s"] > 0 and timing["compute_time"]["steps"] > 0


def test_split_keeps_every_key_once() -> None:
    runs = [{"scenario": "s", "controller": "c", "wall_time_s": 1.0, "tracking": {"e": 1}}]
    inputs_only, machine = split_machine_keys(runs)
    assert inputs_only == [{"scenario": "s", "controller": "c", "tracking": {"e": 1}}]
    assert machine == [{"scenario": "s", "controller": "c", "wall_time_s": 1.0}]

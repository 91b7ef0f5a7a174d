"""Studies commit what their inputs decide and put what the machine decides (wall and
step times, the host) under results/logs/, so that a rerun of the same code rewrites the
same bytes (studies/machine_figures.py; tables, run, identification, vehicle variants)."""
from __future__ import annotations

from studies.machine_figures import MACHINE_KEYS, split_machine_keys
from studies.vehicle_variants_report import inputs_only


def _run(seconds: float) -> dict:
    return {"scenario": "dlc_low_mu", "controller": "lmpc", "completed": True, "seconds": seconds,
            "compute_time": {"median_s": seconds / 100}, "tracking": {"lateral_error_m": {"rmse": 0.02}}}


def test_split_leaves_no_machine_figure_in_the_committed_part() -> None:
    committed, machine = split_machine_keys([_run(0.6), _run(0.4)])
    assert committed[0] == committed[1] and not set(committed[0]) & set(MACHINE_KEYS)
    assert [m["seconds"] for m in machine] == [0.6, 0.4] and machine[0]["controller"] == "lmpc"


def test_a_variant_result_keeps_the_same_bytes_whatever_its_times() -> None:
    def result(seconds: float) -> dict:
        return {"variant": "van", "seconds": {"drive": seconds, "training": 2 * seconds},
                "drive": {"seconds": seconds, "tracking": {"lateral_error_m": {"max_abs": 0.1}}},
                "runs": [_run(seconds)]}
    fast, slow = inputs_only(result(1.0)), inputs_only(result(9.0))
    assert fast == slow
    assert "seconds" not in fast and "seconds" not in fast["drive"]
    assert fast["drive"]["tracking"] == {"lateral_error_m": {"max_abs": 0.1}}

"""studies.results_compare: results compared value by value, machine figures left out."""
from __future__ import annotations

import math

from studies.results_compare import csv_rows, differences, is_machine_field, main


def test_machine_fields_are_left_out_and_results_are_not() -> None:
    for name in ("wall_time_s", "compute_time", "step_p99_us", "overruns", "solver_share", "key"):
        assert is_machine_field(name), name
    for name in ("e_y_rmse", "completed", "heading_rmse", "mu", "controller", "at_ms"):
        assert not is_machine_field(name), name


def test_differences_name_each_changed_value_to_the_last_bit() -> None:
    old = {"runs": [{"e_y_rmse": 0.1, "wall_time_s": 1.0, "nan": math.nan}], "only_old": 1}
    new = {"runs": [{"e_y_rmse": math.nextafter(0.1, 1.0), "wall_time_s": 9.0, "nan": math.nan}]}
    assert list(differences(old, new)) == [".only_old: only in REV",
                                           ".runs[0].e_y_rmse: 0.1 -> 0.10000000000000002"]
    assert list(differences({"a": [1, 2]}, {"a": [1]})) == [".a: 2 items, now 1"]


def test_csv_rows_drop_machine_columns() -> None:
    rows = csv_rows("controller,e_y_rmse,wall_s,step_p99_us\nlmpc,0.01,1.2,300\n")
    assert rows == [{"controller": "lmpc", "e_y_rmse": "0.01"}]


def test_an_unknown_revision_is_a_usage_error(capsys) -> None:
    assert main(["no-such-revision-0000"]) == 2
    assert "not a revision" in capsys.readouterr().err

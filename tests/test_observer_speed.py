"""The observer-speed study (studies/observer_speed.py): its grid, its tallies, its refusals."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

from controller.tuning import load_tuning
from hil.errors import HilError
from studies import observer_speed
from studies.campaign.grid import load_grid
from studies.tuning_sweep_executor import Evaluation


def test_the_grid_runs_the_study_s_poles_and_dkmpc_once() -> None:
    grid = load_grid(observer_speed.GRID)
    tunings = {name: grid.tunings.get(name, ()) for name in dict.fromkeys(c.tuning for c in grid.cells)}
    file_pole = load_tuning().eso_dkmpc.eso_second_pole
    poles = observer_speed.grid_poles(tunings, file_pole)
    assert sorted(poles.values()) == [0.85, 0.9, 0.95, 0.98]  # docs/eso.md's table
    assert poles["file"] == file_pole
    dkmpc = [c for c in grid.cells if c.controller == "dkmpc"]
    assert {c.tuning for c in dkmpc} == {"file"} and len(dkmpc) == 96
    assert len(grid.cells) == 96 * (len(poles) + 1)


def test_a_tuning_that_sets_more_than_the_pole_is_refused() -> None:
    with pytest.raises(HilError, match="must set eso_second_pole only"):
        observer_speed.grid_poles({"x": (("eso_second_pole", 0.9), ("q_yaw", 40.0))}, 0.95)


def _row(controller: str, tuning: str, mass: float, lag: float, rmse: float | None, mu: float = 0.85) -> dict:
    return {"controller": controller, "tuning": tuning, "scenario": "dlc_high_mu", "mu": mu, "speed": 30.0,
            "mass_offset_kg": mass, "lag_factor": lag, "completed": int(rmse is not None),
            "e_y_rmse": 3.0 if rmse is None else rmse, "e_y_max": 0.1, "heading_rmse": 0.01, "error": ""}


def test_pole_rows_count_head_to_head_and_the_nominal_ratio_per_pole() -> None:
    rows = [
        _row("dkmpc", "file", 0.0, 1.0, 0.010), _row("dkmpc", "file", 300.0, 1.0, 0.020),
        _row("dkmpc", "file", 0.0, 3.0, None), _row("dkmpc", "file", 0.0, 1.0, 0.010, mu=0.3),
        # the file's pole: worse on the nominal cells, better on the heavy one, completes the lagging one
        _row("eso-dkmpc", "file", 0.0, 1.0, 0.012), _row("eso-dkmpc", "file", 300.0, 1.0, 0.015),
        _row("eso-dkmpc", "file", 0.0, 3.0, 0.030), _row("eso-dkmpc", "file", 0.0, 1.0, 0.011, mu=0.3),
        # a faster pole: equal on one nominal cell (a tie), loses the lagging one as well
        _row("eso-dkmpc", "fast", 0.0, 1.0, 0.010), _row("eso-dkmpc", "fast", 300.0, 1.0, 0.025),
        _row("eso-dkmpc", "fast", 0.0, 3.0, None), _row("eso-dkmpc", "fast", 0.0, 1.0, 0.014, mu=0.3),
    ]
    table = observer_speed.pole_rows(rows, {"file": 0.95, "fast": 0.9}, {0.95: 0.026, 0.9: 0.027})
    assert [r.pole for r in table] == [0.9, 0.95]
    fast, file = table
    assert (file.mismatch.wins, file.mismatch.losses, file.mismatch.cells) == (2, 0, 2)
    assert (file.every.wins, file.every.losses, file.every.cells) == (2, 2, 4)
    assert file.nominal_cells == 2 and file.nominal_ratio_max == pytest.approx(1.2)
    assert file.nominal_ratio_mean == pytest.approx((1.2 + 1.1) / 2)
    # the lagging cell neither completed: left out of the head to head
    assert (fast.mismatch.wins, fast.mismatch.losses, fast.mismatch.cells) == (0, 1, 1)
    assert (fast.every.wins, fast.every.losses, fast.every.cells) == (0, 2, 3)
    assert fast.nominal_ratio_max == pytest.approx(1.4) and fast.tuning_objective_m == 0.027
    text = observer_speed.report_markdown(table, 0.95, [], command="test", seconds=1.0)
    assert "| 0.95 (tuning file) | 2 of 2 (DKMPC lower on 0) |" in text
    assert "lowest at 0.95" in text


def test_nominal_ratio_is_nan_without_a_nominal_cell_both_completed() -> None:
    rows = [_row("dkmpc", "file", 0.0, 1.0, None), _row("eso-dkmpc", "file", 0.0, 1.0, 0.01),
            _row("dkmpc", "file", 300.0, 1.0, 0.02), _row("eso-dkmpc", "file", 300.0, 1.0, 0.01)]
    (row,) = observer_speed.pole_rows(rows, {"file": 0.95}, {0.95: 0.02})
    assert row.nominal_cells == 0 and math.isnan(row.nominal_ratio_max)


def test_the_command_refuses_a_folder_without_a_campaign(tmp_path: Path, capsys) -> None:
    status = observer_speed.main(["--campaign", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
    assert status == 1
    assert "no campaign there" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_changed_plants_are_the_observer_stage_s_undisturbed_runs_on_a_heavier_car_and_slower_steering() -> None:
    from models.vehicle_params import load_vehicle_params
    from studies.campaign.closed_loop_cell import plant_for

    scenarios = observer_speed.changed_plant_set()
    assert len(scenarios) == 22 and len({s.name for s in scenarios}) == 22
    heavy = [s for s in scenarios if s.name.endswith("+mass+150kg")]
    slow = [s for s in scenarios if s.name.endswith("+lag_x2")]
    assert len(heavy) == len(slow) == 11
    assert not any(s.disturbances.any for s in scenarios)
    nominal = load_vehicle_params()
    heavy_plant, _ = plant_for(heavy[0])
    slow_plant, _ = plant_for(slow[0])
    assert heavy_plant.params.mass == pytest.approx(nominal.mass + 150.0)
    assert heavy_plant.params.steer_time_constant == pytest.approx(nominal.steer_time_constant)
    assert slow_plant.params.mass == pytest.approx(nominal.mass)
    assert slow_plant.params.steer_time_constant == pytest.approx(2 * nominal.steer_time_constant)


def _evaluation(controller: str, setting: tuple, rmse: dict[str, float | None]) -> Evaluation:
    from studies.tuning_sweep_executor import objective

    values = {n: (v if v is not None else float("nan")) for n, v in rmse.items()}
    completed = {n: v is not None for n, v in rmse.items()}
    return Evaluation(controller, "observer", setting, values, dict(values), completed,
                      {n: None for n in rmse}, objective(values, completed), 1.0)


def test_changed_plant_rows_average_per_plant_and_with_the_tuning_set() -> None:
    tuning = {0.95: _evaluation("eso-dkmpc", (("eso_second_pole", 0.95),), {"a": 0.010, "a+disturbed": 0.030}),
              0.9: _evaluation("eso-dkmpc", (("eso_second_pole", 0.9),), {"a": 0.012, "a+disturbed": 0.032})}
    changed = [
        _evaluation("eso-dkmpc", (("eso_second_pole", 0.9),), {"a+mass+150kg": 0.010, "a+lag_x2": 0.014}),
        _evaluation("eso-dkmpc", (("eso_second_pole", 0.95),), {"a+mass+150kg": 0.012, "a+lag_x2": None}),
        _evaluation("dkmpc", (), {"a+mass+150kg": 0.011, "a+lag_x2": 0.013}),
    ]
    fast, slow, baseline = observer_speed.changed_plant_rows(changed, tuning)
    assert fast.per_plant_m == pytest.approx({"mass+150kg": 0.010, "lag_x2": 0.014})
    assert fast.objective_m == pytest.approx(0.012)
    assert fast.with_tuning_set_m == pytest.approx((0.012 + 0.032 + 0.010 + 0.014) / 4)
    # a run that did not complete counts the objective's penalty, per plant too
    assert slow.per_plant_m["lag_x2"] > 1.0 and slow.with_tuning_set_m > 0.25
    assert baseline.pole is None and math.isnan(baseline.with_tuning_set_m)
    text = "\n".join(observer_speed.changed_plant_markdown([fast, slow, baseline]))
    assert "| ESO-DKMPC 0.9 | 10.00 | 14.00 | 12.00 | 17.00 |" in text
    assert "| DKMPC | 11.00 | 13.00 | 12.00 | - |" in text
    assert "With the changed plants added, the objective is lowest at 0.9" in text
    assert "ESO-DKMPC is lower at no pole" in text

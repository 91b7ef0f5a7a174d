"""The tuning sweep on the campaign engine (``studies.tuning_sweep_cells``, the grids
``tuning_sweep`` and ``tuning_sweep_smoke``, the engine's ``tuning`` axis): a cell with a
tuning override is, to the last bit, the run the sweep made before it ran on the engine (the
controller built from the tuning file with the setting's fields replaced, run by
``studies.closed_loop.run_closed_loop`` on the scenario file).

The smoke check (8 closed-loop runs of 10 s, about 10 s in all)::

    .venv/bin/python -m pytest -q tests/test_tuning_sweep_cells.py -k smoke -s
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from tqdm import tqdm

from controller.tuning import load_tuning
from hil.errors import StudyError
from hil.scenario import Scenario
from studies.campaign.executors import SerialExecutor
from studies.campaign.grid import GridError, load_grid
from studies.campaign.runner import cell_job, code_version, run_campaign
from studies.closed_loop import run_closed_loop
from studies.tuning_set import tuning_scenarios
from studies.tuning_sweep_cells import CampaignSweepExecutor, sweep_grid
from studies.tuning_sweep_executor import SweepExecutor, build_controller
from studies.tuning_sweep_grids import with_setting

ROOT = Path(__file__).resolve().parent.parent
SMOKE_SCENARIOS = ["tuning_40kmh_mu085", "tuning_60kmh_mu04"]
SOFT = (("q_position", 3.0), ("q_yaw", 80.0), ("r_steer", 0.3), ("p_steer_rate", 300.0))
STIFF = (("q_position", 30.0), ("q_yaw", 20.0), ("r_steer", 3.0), ("p_steer_rate", 300.0))
OBSERVER = (("eso_pole", 0.0), ("eso_second_pole", 0.995), ("disturbance_decay", 0.8))
#: The smoke subset of the sweep: 2 settings x 2 controllers (one with an observer, whose
#: observer fields are swept too, one with a speed schedule set apart).
SMOKE_JOBS = [("lmpc", "weights", SOFT), ("lmpc", "low-speed", STIFF + (("low_speed_q_position", 1.0),)),
              ("eso-dkmpc", "weights", SOFT + OBSERVER), ("eso-dkmpc", "weights", STIFF + OBSERVER)]


def _direct(controller: str, setting: tuple, scenario: Scenario) -> tuple[float, float, bool]:
    """The sweep's run before the engine: e_Y RMSE, max |e_Y|, completed."""
    result = run_closed_loop(scenario, build_controller(controller, with_setting(load_tuning(), controller, setting)))
    return float(result.tracking.lateral.rmse), float(result.tracking.lateral.max_abs), bool(result.completed)


@pytest.mark.slow
def test_smoke_grid_cells_equal_the_direct_runs_bit_for_bit(tmp_path: Path) -> None:
    """The grid tuning_sweep_smoke on the engine (in this process, then again from its
    cache) against the direct runs of the same controllers, settings and scenario files."""
    grid = load_grid("tuning_sweep_smoke")
    assert len(grid.cells) == 8 and {c.runner for c in grid.cells} == {"closed_loop"}
    first = run_campaign(grid, tmp_path, SerialExecutor(_run_cell()), progress=False)
    again = run_campaign(grid, tmp_path, SerialExecutor(_run_cell()), progress=False)
    assert (first.computed, again.cached) == (8, 8)
    worst = 0.0
    for cell, row, cached in zip(grid.cells, first.rows, again.rows):
        scenario = Scenario.load(grid.scenario_files[cell.scenario])
        rmse, max_abs, completed = _direct(cell.controller, grid.tunings[cell.tuning], scenario)
        worst = max(worst, abs(row["e_y_rmse"] - rmse), abs(row["e_y_max"] - max_abs))
        assert (row["e_y_rmse"], row["e_y_max"], bool(row["completed"])) == (rmse, max_abs, completed), cell.label
        assert (cached["e_y_rmse"], cached["e_y_max"]) == (rmse, max_abs)
    print(f"max |engine - direct| over e_Y RMSE and max |e_Y|: {worst:.1e} m")
    assert len({row["e_y_rmse"] for row in first.rows}) == 8  # the overrides did change the runs


@pytest.mark.slow
def test_smoke_sweep_evaluations_equal_the_in_memory_executor_bit_for_bit(tmp_path: Path) -> None:
    """The sweep's smoke subset (SMOKE_JOBS on two tuning scenarios): the engine's
    evaluations (make tune) equal those of the in-memory executor, which runs
    ``run_closed_loop`` on the scenario objects as the sweep did before the engine."""
    scenarios = tuning_scenarios(SMOKE_SCENARIOS)
    engine = CampaignSweepExecutor(scenarios, tuning_file=None, cache=tmp_path, workers=1,
                                   progress=tqdm(disable=True))
    direct = SweepExecutor(scenarios, load_tuning(), run_closed_loop, 1, tqdm(disable=True))
    try:
        ours, theirs = engine.evaluate(SMOKE_JOBS), direct.evaluate(SMOKE_JOBS)
    finally:
        engine.close()
        direct.close()
    for one, two in zip(ours, theirs):
        print(f"{one.controller} {dict(one.setting)['q_position']:g}: objective {one.objective_m!r} m "
              f"(in-memory {two.objective_m!r} m)")
        assert (one.controller, one.stage, one.setting) == (two.controller, two.stage, two.setting)
        assert (one.objective_m, one.rmse_m, one.max_abs_m, one.completed, one.failure) == \
            (two.objective_m, two.rmse_m, two.max_abs_m, two.completed, two.failure)
    assert ours[0].objective_m != ours[1].objective_m and all(math.isfinite(e.objective_m) for e in ours)


def _run_cell():
    from studies.campaign.cell import run_cell

    return run_cell


def test_override_names_the_cell_key_and_leaves_other_grids_keys_alone() -> None:
    grid = load_grid("tuning_sweep_smoke")
    version = "v"
    keys = [cell_job(grid, cell, version).key for cell in grid.cells]
    assert len(set(keys)) == len(grid.cells)
    # The same names for the other overrides: other keys (the values are in the key).
    swapped = dataclasses.replace(grid, tunings={"soft": grid.tunings["stiff"], "stiff": grid.tunings["soft"]})
    assert not {cell_job(swapped, cell, version).key for cell in grid.cells} & set(keys)
    plain = load_grid("robustness_closed_loop_smoke")
    job = cell_job(plain, plain.cells[0], code_version())
    assert job.tuning_toml is None and job.tuning_override == () and job.leave_road_m is None


def test_grid_refuses_bad_tuning_axes(tmp_path: Path) -> None:
    base = (ROOT / "studies/campaign/grids/tuning_sweep_smoke.toml").read_text()
    cases = {
        "over CAN": (base.replace('runner = "closed_loop"', 'runner = "hil"'), "closed_loop"),
        "no table": (base.replace('tuning = ["soft", "stiff"]', 'tuning = ["soft", "hard"]'), "hard"),
        "not a number": (base.replace("q_yaw = 80.0", 'q_yaw = "high"'), "tunings.soft.q_yaw"),
        "no such field": (base.replace("q_yaw = 80.0", "q_yaw = 80.0\nstanley_gain = 1.0"), "stanley_gain"),
        "bad limit": (base.replace("leave_road_m = 10.0", "leave_road_m = -1.0"), "leave_road_m"),
        "no tuning file": (base.replace("[run]", '[run]\ntuning_file = "no/such.toml"'), "tuning_file"),
    }
    for name, (text, named) in cases.items():
        file = tmp_path / "grid.toml"
        file.write_text(text.replace('"hil/scenarios/tuning/', f'"{ROOT}/hil/scenarios/tuning/'))
        with pytest.raises(GridError, match=named):
            load_grid(file)
        print(f"{name}: refused")


def test_sweep_grid_refuses_a_scenario_changed_in_memory() -> None:
    (scenario,) = tuning_scenarios(SMOKE_SCENARIOS[:1])
    grid, values = sweep_grid([scenario])
    assert values == {scenario.name: "hil/scenarios/tuning/tuning_40kmh_mu085.toml"}
    assert grid.leave_road_m == 10.0 and grid.tuning_file is None
    with pytest.raises(StudyError, match="differs from its file"):
        sweep_grid([dataclasses.replace(scenario, duration_s=2.0)])

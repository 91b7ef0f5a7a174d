"""studies.robustness_grid (``make robustness``): the grid file on the campaign engine's
closed_loop runner, the slalom path, the plant of a cell, failures, and the report's
bookkeeping.

No test here compares controllers: the summary is checked on made-up records, and the
real runs only have to produce rows.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.reference import ReferencePath
from hil.path_files import (MAX_POINT_SPACING_M, SLALOM, SLALOM_PATH_FILE, format_path_csv,
                            read_path_csv, slalom_curve, slalom_points)
from hil.scenario import Scenario, load_scenario
from models.vehicle import VehicleCommand
from models.vehicle_params import load_vehicle_params
from studies import robustness_grid, robustness_report, robustness_summary
from studies.campaign import closed_loop_cell
from studies.campaign.cell import LEAVE_ROAD_M, run_cell
from studies.campaign.grid import CLOSED_LOOP_RUNNER, Grid, load_grid, to_toml
from studies.campaign.runner import cell_job, code_version
from studies.robustness_cells import GRID, GRID_CONTROLLERS, MANOEUVRES, MARGIN_S, SETTLE_M, SMOKE_GRID, Cell
from studies.robustness_records import CSV_FIELDS, RunRecord, records_from_rows
from tests.test_closed_loop_doubles import ScriptedController


def _grid_cell(grid: Grid, controller: str, cell: Cell) -> Any:
    """The campaign cell of ``grid`` for ``controller`` on the robustness ``cell``."""
    scenario = MANOEUVRES[cell.manoeuvre].scenario
    [found] = [c for c in grid.cells if (c.controller, c.scenario, c.mu, c.speed, c.mass_offset_kg, c.lag_factor)
               == (controller, scenario, cell.mu, cell.speed_kmh, cell.mass_offset_kg, cell.lag_factor)]
    return found


def _scenario(grid: Grid, cell: Any, tmp_path: Path) -> Scenario:
    file = tmp_path / f"{abs(hash(cell))}.toml"
    file.write_text(to_toml(grid.scenario_document(cell)))
    return Scenario.load(file)


# --- the grid ---------------------------------------------------------------------------


def test_the_grid_file_expands_to_the_documented_cells() -> None:
    grid = load_grid(GRID)
    print(f"{len(grid.cells)} runs of {grid.name}")
    assert len(grid.cells) == 96 * len(GRID_CONTROLLERS) == 576
    assert {c.runner for c in grid.cells} == {CLOSED_LOOP_RUNNER}
    assert {c.mu for c in grid.cells} == {0.3, 0.5, 0.85, 1.0}
    assert {c.speed for c in grid.cells} == {30.0, 50.0, 70.0}
    assert {c.mass_offset_kg for c in grid.cells} == {0.0, 300.0}
    assert {c.lag_factor for c in grid.cells} == {1.0, 3.0}
    assert {c.scenario for c in grid.cells} == {m.scenario for m in MANOEUVRES.values()}
    assert tuple(dict.fromkeys(c.controller for c in grid.cells)) == GRID_CONTROLLERS
    assert GRID_CONTROLLERS == ("eso-dkmpc", "dkmpc", "lmpc", "nmpc", "lmpc-eso", "dmdc-eso")
    # The run length the report states: the course, SETTLE_M to settle, MARGIN_S.
    assert grid.margin_s == MARGIN_S
    for manoeuvre in MANOEUVRES.values():
        assert grid.distance_for(manoeuvre.scenario) == manoeuvre.course_end_x_m + SETTLE_M
    smoke = load_grid(SMOKE_GRID)
    assert len(smoke.cells) == 4 and {c.runner for c in smoke.cells} == {CLOSED_LOOP_RUNNER}


def test_every_cell_is_a_scenario_whose_path_outlasts_the_run(tmp_path: Path) -> None:
    grid = load_grid(GRID)
    for cell in grid.cells:
        if cell.controller != "lmpc":
            continue  # the same scenario for every controller
        scenario = _scenario(grid, cell, tmp_path)
        speed = cell.speed / 3.6
        end = grid.distance_for(cell.scenario)
        assert scenario.start.speed_mps == pytest.approx(speed) and scenario.start.x_m == 0.0
        assert scenario.target_speed(0.0) == scenario.target_speed(30.0) == pytest.approx(speed)
        assert scenario.mu == cell.mu and scenario.mass_offset_kg == cell.mass_offset_kg
        assert speed * scenario.duration_s >= end  # the whole course plus the settling straight
        assert scenario.path_points()[-1, 0] >= speed * scenario.duration_s + 15.0  # + the horizons


# --- the slalom -------------------------------------------------------------------------


def test_the_slalom_path_is_valid_and_the_shipped_file_is_the_generated_one() -> None:
    """Regenerate with: python -m hil.path_files --path slalom (make slalom-path)."""
    assert SLALOM_PATH_FILE.read_text() == format_path_csv(slalom_points())
    points = read_path_csv(SLALOM_PATH_FILE)
    spacing = np.hypot(np.diff(points[:, 0]), np.diff(points[:, 1]))
    path = ReferencePath.from_csv(SLALOM_PATH_FILE)
    curvature = np.gradient(path.yaw, path.s)
    print(f"{len(points)} points, spacing {spacing.min():.3f} .. {spacing.max():.3f} m, "
          f"|Y| <= {np.abs(points[:, 1]).max():.3f} m, |curvature| <= {np.abs(curvature).max():.4f} 1/m")
    assert spacing.max() <= MAX_POINT_SPACING_M and np.all(np.diff(points[:, 0]) > 0)
    # The path passes the cones alternately, 1 m to the side, left of the first.
    y_cones, yaw_cones = slalom_curve(SLALOM.cone_x_m)
    np.testing.assert_allclose(y_cones, SLALOM.offset_m * (-1.0) ** np.arange(SLALOM.cone_count),
                               atol=1e-12)
    np.testing.assert_allclose(yaw_cones, 0.0, atol=1e-12)
    assert np.abs(points[:, 1]).max() <= SLALOM.offset_m + 0.2
    # Straight on Y = 0 before the entry and after the exit (start at X = 0 on the path).
    outside = (points[:, 0] <= SLALOM.entry_x_m) | (points[:, 0] >= SLALOM.exit_x_m)
    assert np.abs(points[outside, 1:]).max() < 1e-9
    assert points[0, 0] <= -20.0 and SLALOM.entry_x_m >= 10.0
    # yaw is the tangent, and the curvature has no jumps (smooth entry and exit): on a 1 cm
    # grid it changes by less than 1e-4 1/m per point (a jump at the envelope's ends would
    # be of the order of the curvature itself, 0.02 1/m).
    x = np.linspace(SLALOM.x_start_m, SLALOM.x_end_m, 27001)
    y, yaw = slalom_curve(x)
    fine_curvature = np.gradient(yaw, x) * np.cos(yaw)
    gap = np.max(np.abs(yaw - np.arctan(np.gradient(y, x))))
    step = np.abs(np.diff(fine_curvature)).max()
    print(f"max |yaw - atan(dY/dX)| = {gap:.2e} rad, max curvature step per cm {step:.2e} 1/m")
    assert gap < 1e-6
    assert step < 1e-4
    assert np.abs(curvature).max() < 0.03


# --- the plant of a cell ----------------------------------------------------------------


def _plant(cell: Cell, tmp_path: Path) -> Any:
    grid = load_grid(GRID)
    plant, command_type = closed_loop_cell.plant_for(_scenario(grid, _grid_cell(grid, "lmpc", cell), tmp_path))
    assert command_type is VehicleCommand
    return plant


def _time_to_reach(plant: Any, speed_kmh: float, angle: float, command: float) -> float:
    plant.reset(vx=speed_kmh / 3.6)
    dt = 0.001
    for k in range(1, 2000):
        plant.step(VehicleCommand(drive_torque=0.0, steer_angle=command), dt)
        if plant.outputs().steer_angle >= angle:
            return k * dt
    return math.inf


def test_the_lag_factor_slows_the_plants_steering_and_keeps_its_rate_limit(tmp_path: Path) -> None:
    nominal = load_vehicle_params()
    fast = _plant(Cell("dlc", 0.85, 50.0, 0.0, 1.0), tmp_path)
    slow = _plant(Cell("dlc", 0.85, 50.0, 0.0, 3.0), tmp_path)
    assert fast.params.steer_time_constant == nominal.steer_time_constant
    assert slow.params.steer_time_constant == pytest.approx(3 * nominal.steer_time_constant)
    assert slow.params.steer_rate_limit == nominal.steer_rate_limit
    # A 0.02 rad step (below the rate limit for both): 63 % of it after one time constant.
    t_fast = _time_to_reach(fast, 50.0, 0.63 * 0.02, 0.02)
    t_slow = _time_to_reach(slow, 50.0, 0.63 * 0.02, 0.02)
    print(f"63 % of a 0.02 rad steering step: x1 after {t_fast * 1e3:.0f} ms, x3 after {t_slow * 1e3:.0f} ms")
    assert t_fast == pytest.approx(nominal.steer_time_constant, rel=0.15)
    assert t_slow == pytest.approx(3 * nominal.steer_time_constant, rel=0.15)


def test_mass_and_mu_reach_the_plant(tmp_path: Path) -> None:
    nominal = load_vehicle_params()
    params = _plant(Cell("slalom", 0.3, 30.0, 300.0, 1.0), tmp_path).params
    assert params.mass == nominal.mass + 300.0 and params.mu == 0.3
    assert params.yaw_inertia == nominal.yaw_inertia


# --- runs -------------------------------------------------------------------------------


def _run(grid: Grid, controller: str, cell: Cell) -> dict[str, Any]:
    found = _grid_cell(grid, controller, cell)
    return {**found.as_dict(), **run_cell(cell_job(grid, found, code_version()))}


def test_a_tiny_real_run_produces_rows(tmp_path: Path) -> None:
    grid, cell = load_grid(GRID), Cell("dlc", 1.0, 70.0, 0.0, 1.0)
    rows = [_run(grid, name, cell) for name in ("dkmpc", "lmpc")]
    records = records_from_rows(rows, ["lmpc", "dkmpc"])
    for record in records:
        print(f"{record.controller}: completed {record.completed}, e_Y RMSE {record.e_y_rmse:.4f} m, "
              f"max {record.e_y_max:.3f} m, {record.steps} steps, {record.seconds:.1f} s {record.error}")
    assert [(r.controller, r.cell) for r in records] == [("lmpc", cell), ("dkmpc", cell)]
    scenario = _scenario(grid, _grid_cell(grid, "lmpc", cell), tmp_path)
    for record in records:
        assert record.steps > 0 and math.isfinite(record.e_y_rmse) and math.isfinite(record.heading_rmse)
        assert record.completed == (record.error == "")
        if record.completed:
            assert record.e_y_max <= LEAVE_ROAD_M
            assert record.steps == round(scenario.duration_s / 0.025)
    robustness_report.write_outputs(records, ["lmpc", "dkmpc"], tmp_path / "out", command="test")
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        csv_rows = list(csv.DictReader(handle))
    assert len(csv_rows) == 2 and tuple(csv_rows[0]) == CSV_FIELDS
    assert csv_rows[0]["manoeuvre"] == "dlc" and csv_rows[0]["speed_kmh"] == "70"
    assert "## (b)" in (tmp_path / "out" / "robustness.md").read_text()
    assert (tmp_path / "out" / "robustness.png").stat().st_size > 10_000


def double_controller(name: str, model: Any) -> ScriptedController:
    """Stands in for the registry: ``lmpc`` steers 0 (leaves the road in a lane change),
    ``dkmpc`` raises at its fourth step, ``nmpc`` cannot be built."""
    if name == "lmpc":
        return ScriptedController(lambda k: 0.0)
    if name == "dkmpc":
        return ScriptedController(lambda k: 0.0, raise_at=3)
    raise RuntimeError(f"cannot build {name}")


def test_a_run_that_leaves_the_road_or_fails_is_recorded_and_the_grid_goes_on(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(closed_loop_cell, "controller_for", double_controller)
    grid, cell = load_grid(GRID), Cell("dlc", 1.0, 70.0, 0.0, 1.0)
    names = ["nmpc", "lmpc", "dkmpc"]
    records = records_from_rows([_run(grid, name, cell) for name in names], names)
    by_name = {r.controller: r for r in records}
    for record in records:
        print(f"{record.controller}: {record.error}")
    unbuildable = by_name["nmpc"]
    assert not unbuildable.completed and unbuildable.not_run and unbuildable.steps == 0
    assert unbuildable.error == "RuntimeError: cannot build nmpc"
    assert math.isnan(unbuildable.e_y_rmse)
    straight = by_name["lmpc"]
    assert not straight.completed and not straight.not_run
    assert straight.error.startswith("stopped: |e_Y| = ") and "> 2.0 m" in straight.error
    assert straight.e_y_max > LEAVE_ROAD_M
    raised = by_name["dkmpc"]
    assert not raised.completed and "controller.step raised" in raised.error
    summary = robustness_report.write_outputs(records, names, tmp_path / "out", command="test")
    assert summary.common_cells == ()
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "no ranking" in text and "Runs that could not be built (1)" in text
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        rows = {row["controller"]: row for row in csv.DictReader(handle)}
    assert rows["nmpc"]["e_y_rmse"] == "" and rows["nmpc"]["completed"] == "0"


def test_the_grid_refuses_bus_faults_on_the_closed_loop_runner(tmp_path: Path) -> None:
    from studies.campaign.grid import GridError, fault_catalogue

    file = tmp_path / "g.toml"
    fault = next(iter(fault_catalogue()))  # a case of make faults
    file.write_text(f'[axes]\ncontroller = "lmpc"\nscenario = "dlc_high_mu"\nrunner = "closed_loop"\n'
                    f'fault = ["none", "{fault}"]\n')
    with pytest.raises(GridError, match="no bus"):
        load_grid(file)
    file.write_text('[axes]\ncontroller = "lmpc"\nscenario = "dlc_high_mu"\nrunner = "by hand"\n')
    with pytest.raises(GridError, match="unknown runner; choose from hil, closed_loop"):
        load_grid(file)
    file.write_text('[axes]\ncontroller = "lmpc"\nscenario = "dlc_high_mu"\nrunner = ["hil", "closed_loop"]\n'
                    'ecu = ["python", "c"]\n')
    grid = load_grid(file)  # the C ECU needs the bus: its closed_loop cell is left out
    assert sorted((c.runner, c.ecu) for c in grid.cells) == [("closed_loop", "python"), ("hil", "c"),
                                                             ("hil", "python")]
    assert grid.c_left_out == {"the closed_loop runner has no bus for the C ECU": 1}


def test_the_grip_margin_grid_runs_make_identifys_changed_plant(tmp_path: Path) -> None:
    """make grip-margin's cells (a scenario file with the mass and the rear tyres, the lag
    axis x3) build make identify's changed plant, parameter for parameter."""
    import dataclasses

    from studies.identification import changed_params

    grid = load_grid("grip_margin")
    cell = next(c for c in grid.cells if c.controller == "lmpc")
    plant, _ = closed_loop_cell.plant_for(_scenario(grid, cell, tmp_path))
    assert dataclasses.asdict(plant.params) == pytest.approx(
        dataclasses.asdict(changed_params(load_scenario("dlc_low_mu").vehicle_params())), rel=1e-12)


def test_the_report_names_a_campaign_that_is_missing_or_not_computed(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert robustness_grid.main([SMOKE_GRID, "--campaign", str(tmp_path / "none"), "--out", str(tmp_path)]) == 1
    assert "no campaign there" in capsys.readouterr().err
    (tmp_path / "empty" / "cache").mkdir(parents=True)
    assert robustness_grid.main([SMOKE_GRID, "--campaign", str(tmp_path / "empty"), "--out", str(tmp_path)]) == 1
    assert "4 of the 4 runs" in capsys.readouterr().err
    assert not (tmp_path / "robustness.md").exists()


@pytest.mark.slow
def test_the_smoke_grid_runs_on_two_workers_and_again_from_the_cache(tmp_path: Path) -> None:
    """``make robustness-smoke``: 2 controllers x 2 cells on spawned workers, then again
    from the cache."""
    from studies.campaign.__main__ import main as campaign

    argv = [SMOKE_GRID, "--out", str(tmp_path / "campaign"), "--workers", "2", "--no-progress"]
    assert campaign(argv) == 0
    report = [SMOKE_GRID, "--campaign", str(tmp_path / "campaign"), "--out", str(tmp_path / "out")]
    assert robustness_grid.main(report) == 0
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and {r["controller"] for r in rows} == {"lmpc", "dkmpc"}
    assert len(list((tmp_path / "campaign" / "cache").glob("*.json"))) == 4
    first = (tmp_path / "out" / "robustness.csv").read_text()
    assert campaign(argv) == 0 and robustness_grid.main(report) == 0
    assert (tmp_path / "out" / "robustness.csv").read_text() == first


# --- the summary, on made-up records ----------------------------------------------------


def _record(controller: str, cell: Cell, rmse: float | None) -> RunRecord:
    completed = rmse is not None
    value = rmse if completed else 3.0
    return RunRecord(controller, *cell.as_dict().values(), completed=completed, e_y_rmse=value,
                     e_y_max=2 * value, heading_rmse=0.01, error="" if completed else "left", steps=10)


def test_the_summary_uses_only_the_cells_every_controller_completed() -> None:
    a, b, c = (Cell("dlc", 0.85, 30.0, 0.0, 1.0), Cell("slalom", 0.85, 30.0, 300.0, 3.0),
               Cell("dlc", 0.3, 70.0, 0.0, 1.0))
    records = [_record("p", a, 0.1), _record("q", a, 0.2),
               _record("p", b, 0.4), _record("q", b, 0.3),
               _record("p", c, 0.05), _record("q", c, None)]
    summary = robustness_summary.summarise(records, ["p", "q"])
    assert summary.common_cells == (a, b)
    rows = {row.controller: row for row in summary.rows}
    assert rows["p"].completed == 3 and rows["q"].completed == 2
    assert rows["p"].completed_by_manoeuvre == {"dlc": 2, "slalom": 1}
    assert rows["p"].common_rmse_mean == pytest.approx(0.25)  # c is left out
    assert rows["q"].common_rmse_median == pytest.approx(0.25)
    assert rows["p"].lowest_count == rows["q"].lowest_count == 1
    count, values = summary.pivot[(0.85, 30.0)]
    assert count == 2 and values == {"p": pytest.approx(0.25), "q": pytest.approx(0.25)}
    assert summary.pivot[(0.3, 70.0)][0] == 0 and math.isnan(summary.pivot[(0.3, 70.0)][1]["p"])
    assert summary.completed_pivot[(0.3, 70.0)] == {"p": 1, "q": 0}
    line = robustness_report.ranking_line(summary)
    assert "over the 2 cells" in line and "p, q (1 of 2 each)" in line


def test_observer_line_counts_eso_dkmpc_against_dkmpc_overall_and_on_mismatch_cells() -> None:
    nominal, heavy, lagging, lost = (Cell("dlc", 0.85, 30.0, 0.0, 1.0), Cell("dlc", 0.85, 30.0, 300.0, 1.0),
                                     Cell("dlc", 0.5, 50.0, 0.0, 3.0), Cell("dlc", 0.3, 70.0, 300.0, 3.0))
    records = [_record("eso-dkmpc", nominal, 0.2), _record("dkmpc", nominal, 0.1),
               _record("eso-dkmpc", heavy, 0.1), _record("dkmpc", heavy, 0.2),
               _record("eso-dkmpc", lagging, 0.3), _record("dkmpc", lagging, None),
               _record("eso-dkmpc", lost, None), _record("dkmpc", lost, None)]  # neither: left out
    line = robustness_report.observer_line(records)
    assert "below DKMPC's on 2 of 3 (DKMPC lower on 1)" in line
    assert "(mass +300 kg or steering lag x3) on 2 of 2 (DKMPC lower on 0)" in line
    assert robustness_report.observer_line([_record("eso-dkmpc", nominal, 0.2)]) is None

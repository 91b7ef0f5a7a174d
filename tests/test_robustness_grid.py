"""studies.robustness_grid (``make robustness``): the grid, the slalom path, the plant of a
cell, the cache, failures, and the report's bookkeeping.

No test here compares controllers: the summary is checked on made-up records, and the
real runs only have to produce rows.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from controller.reference import ReferencePath
from hil.path_files import (MAX_POINT_SPACING_M, SLALOM, SLALOM_PATH_FILE, format_path_csv,
                            read_path_csv, slalom_curve, slalom_points)
from models.vehicle import VehicleCommand
from models.vehicle_params import load_vehicle_params
from studies import robustness_grid as grid
from studies import robustness_runs
from studies.robustness_grid import Cell, RunRecord
from tests.test_closed_loop_doubles import ScriptedController

#: Names the test factory builds (doubles, not controllers of the registry).
CALLS: list[str] = []


def double_factory(name: str) -> ScriptedController:
    """``straight``: steer 0 (leaves the road in a lane change); ``raises-in-step``: raises
    at its fourth step; ``unbuildable``: cannot be built."""
    CALLS.append(name)
    if name == "straight":
        return ScriptedController(lambda k: 0.0)
    if name == "raises-in-step":
        return ScriptedController(lambda k: 0.0, raise_at=3)
    raise RuntimeError(f"cannot build {name}")


# --- the grid ---------------------------------------------------------------------------


def test_the_grid_expands_to_the_documented_cell_count() -> None:
    cells = grid.grid_cells()
    print(f"{len(cells)} cells x {len(grid.GRID_CONTROLLERS)} controllers = "
          f"{len(cells) * len(grid.GRID_CONTROLLERS)} runs")
    assert len(cells) == 4 * 3 * 2 * 2 * 2 == 96
    assert len(set(cells)) == len({c.name for c in cells}) == 96
    assert {c.mu for c in cells} == {0.3, 0.5, 0.85, 1.0}
    assert {c.speed_kmh for c in cells} == {30.0, 50.0, 70.0}
    assert {c.mass_offset_kg for c in cells} == {0.0, 300.0}
    assert {c.lag_factor for c in cells} == {1.0, 3.0}
    assert sum(c.manoeuvre == "dlc" for c in cells) == sum(c.manoeuvre == "slalom" for c in cells) == 48
    assert len(grid.grid_cells(["slalom"])) == 48
    assert grid.GRID_CONTROLLERS == ("eso-dkmpc", "dkmpc", "lmpc", "nmpc", "lmpc-eso", "dmdc-eso")
    with pytest.raises(grid.StudyError, match="unknown manoeuvre"):
        grid.grid_cells(["figure-eight"])


def test_every_cell_is_a_scenario_whose_path_outlasts_the_run() -> None:
    for cell in grid.grid_cells():
        scenario = grid.cell_scenario(cell)
        speed = cell.speed_kmh / 3.6
        end = grid.MANOEUVRES[cell.manoeuvre].course_end_x_m
        assert scenario.start.speed_mps == pytest.approx(speed)
        assert scenario.target_speed(0.0) == scenario.target_speed(30.0) == pytest.approx(speed)
        assert scenario.mu == cell.mu and scenario.mass_offset_kg == cell.mass_offset_kg
        # The whole course plus the settling straight is driven at the target speed.
        assert speed * scenario.duration_s >= end + grid.SETTLE_M
        assert scenario.path_points()[-1, 0] >= speed * scenario.duration_s + grid.HORIZON_ROOM_M


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


def _time_to_reach(cell: Cell, angle: float, command: float) -> float:
    plant, command_type = grid.build_plant(cell)
    assert command_type is VehicleCommand
    plant.reset(vx=cell.speed_kmh / 3.6)
    dt = 0.001
    for k in range(1, 2000):
        plant.step(command_type(drive_torque=0.0, steer_angle=command), dt)
        if plant.outputs().steer_angle >= angle:
            return k * dt
    return math.inf


def test_the_lag_factor_slows_the_plants_steering_and_keeps_its_rate_limit() -> None:
    nominal = load_vehicle_params()
    fast, slow = Cell("dlc", 0.85, 50.0, 0.0, 1.0), Cell("dlc", 0.85, 50.0, 0.0, 3.0)
    assert grid.plant_params(fast).steer_time_constant == nominal.steer_time_constant
    assert grid.plant_params(slow).steer_time_constant == pytest.approx(3 * nominal.steer_time_constant)
    assert grid.plant_params(slow).steer_rate_limit == nominal.steer_rate_limit
    # A 0.02 rad step (below the rate limit for both): 63 % of it after one time constant.
    t_fast = _time_to_reach(fast, 0.63 * 0.02, 0.02)
    t_slow = _time_to_reach(slow, 0.63 * 0.02, 0.02)
    print(f"63 % of a 0.02 rad steering step: x1 after {t_fast * 1e3:.0f} ms, x3 after {t_slow * 1e3:.0f} ms")
    assert t_fast == pytest.approx(nominal.steer_time_constant, rel=0.15)
    assert t_slow == pytest.approx(3 * nominal.steer_time_constant, rel=0.15)


def test_mass_and_mu_reach_the_plant() -> None:
    nominal = load_vehicle_params()
    params = grid.plant_params(Cell("slalom", 0.3, 30.0, 300.0, 1.0))
    assert params.mass == nominal.mass + 300.0 and params.mu == 0.3
    assert params.yaw_inertia == nominal.yaw_inertia


def test_the_cache_key_names_what_a_run_reads() -> None:
    cell = Cell("dlc", 0.85, 50.0, 0.0, 1.0)
    assert grid.run_key(cell, "lmpc") == grid.run_key(Cell("dlc", 0.85, 50.0, 0.0, 1.0), "lmpc")
    keys = {grid.run_key(c, "lmpc") for c in grid.grid_cells()}
    assert len(keys) == 96
    assert grid.run_key(cell, "lmpc") != grid.run_key(cell, "dkmpc")
    inputs = dict(grid.input_digests("eso-dkmpc"))
    for name in ("controller/tuning.toml", "models/vehicle.toml", "models/artifacts/dk_d5.npz",
                 "hil/paths/slalom.csv", "controller/eso_dkmpc.py", "studies/closed_loop.py"):
        assert name in inputs, name


# --- runs -------------------------------------------------------------------------------


def test_a_tiny_real_run_produces_rows(tmp_path: Path) -> None:
    cells = [Cell("dlc", 1.0, 70.0, 0.0, 1.0)]
    records = grid.run_grid(cells, ["lmpc", "dkmpc"], cache_dir=tmp_path / "cache", workers=1,
                            show_progress=False)
    for record in records:
        print(f"{record.controller}: completed {record.completed}, e_Y RMSE {record.e_y_rmse:.4f} m, "
              f"max {record.e_y_max:.3f} m, {record.steps} steps, {record.seconds:.1f} s {record.error}")
    assert [(r.controller, r.cell) for r in records] == [("lmpc", cells[0]), ("dkmpc", cells[0])]
    for record in records:
        assert record.steps > 0 and math.isfinite(record.e_y_rmse) and math.isfinite(record.heading_rmse)
        assert record.completed == (record.error == "")
        if record.completed:
            assert record.e_y_max <= grid.LEAVE_ROAD_M
            assert record.steps == round(grid.run_duration_s(cells[0]) / 0.025)
    # The controllers were built from a copy of the tuning file, named by its digest.
    snapshots = list((tmp_path / "cache" / "tuning").glob("*.toml"))
    assert len(snapshots) == 1
    assert snapshots[0].read_bytes() == (grid.ROOT / "controller" / "tuning.toml").read_bytes()
    grid.write_outputs(records, ["lmpc", "dkmpc"], tmp_path / "out", command="test", workers=1)
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2 and tuple(rows[0]) == grid.CSV_FIELDS
    assert rows[0]["manoeuvre"] == "dlc" and rows[0]["speed_kmh"] == "70"
    assert "## (b)" in (tmp_path / "out" / "robustness.md").read_text()
    assert (tmp_path / "out" / "robustness.png").stat().st_size > 10_000


def test_a_rerun_resumes_from_the_cache(tmp_path: Path) -> None:
    cells = [Cell("dlc", 1.0, 70.0, 0.0, 1.0), Cell("dlc", 0.3, 70.0, 300.0, 3.0)]
    CALLS.clear()
    first = grid.run_grid(cells, ["straight"], cache_dir=tmp_path, workers=1, show_progress=False,
                          factory=double_factory)
    assert CALLS == ["straight", "straight"]
    assert len(list((tmp_path / "runs").glob("*.json"))) == 2
    CALLS.clear()
    again = grid.run_grid(cells, ["straight"], cache_dir=tmp_path, workers=1, show_progress=False,
                          factory=double_factory)
    assert CALLS == [] and again == first
    # A damaged entry is run again, the others still come from the cache.
    next((tmp_path / "runs").glob("*.json")).write_text("{not json")
    grid.run_grid(cells, ["straight"], cache_dir=tmp_path, workers=1, show_progress=False,
                  factory=double_factory)
    assert CALLS == ["straight"]
    grid.run_grid(cells, ["straight"], cache_dir=tmp_path, workers=1, show_progress=False,
                  factory=double_factory, use_cache=False)
    assert CALLS == ["straight"] * 3


def test_a_run_that_leaves_the_road_or_fails_is_recorded_and_the_grid_goes_on(tmp_path: Path) -> None:
    cell = Cell("dlc", 1.0, 70.0, 0.0, 1.0)
    names = ["unbuildable", "straight", "raises-in-step"]
    records = grid.run_grid([cell], names, cache_dir=tmp_path / "cache", workers=1,
                            show_progress=False, factory=double_factory)
    by_name = {r.controller: r for r in records}
    for record in records:
        print(f"{record.controller}: {record.error}")
    unbuildable = by_name["unbuildable"]
    assert not unbuildable.completed and unbuildable.not_run and unbuildable.steps == 0
    assert unbuildable.error == "RuntimeError: cannot build unbuildable"
    assert math.isnan(unbuildable.e_y_rmse)
    straight = by_name["straight"]
    assert not straight.completed and not straight.not_run
    assert straight.error.startswith("stopped: |e_Y| = ") and "> 2.0 m" in straight.error
    assert straight.e_y_max > grid.LEAVE_ROAD_M
    raised = by_name["raises-in-step"]
    assert not raised.completed and "controller.step raised" in raised.error
    summary = grid.write_outputs(records, names, tmp_path / "out", command="test", workers=1)
    assert summary.common_cells == ()
    text = (tmp_path / "out" / "robustness.md").read_text()
    assert "no ranking" in text and "Runs that could not be built (1)" in text
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        rows = {row["controller"]: row for row in csv.DictReader(handle)}
    assert rows["unbuildable"]["e_y_rmse"] == "" and rows["unbuildable"]["completed"] == "0"


def test_inputs_that_change_while_the_grid_runs_drop_its_runs(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    artefact = {"digest": "before"}

    class Digests:
        """Stands in for input_digests: an artefact whose digest the factory changes."""

        def __call__(self, name: str) -> tuple[tuple[str, str], ...]:
            return (("controller/tuning.toml", "t"), ("models/artifacts/x.npz", artefact["digest"]))

        def cache_clear(self) -> None:
            pass

    def retraining_factory(name: str) -> ScriptedController:
        artefact["digest"] = "after"
        return double_factory("straight")

    monkeypatch.setattr(robustness_runs, "input_digests", Digests())  # where run_grid reads it
    cells = [Cell("dlc", 1.0, 70.0, 0.0, 1.0)]
    with pytest.raises(grid.StudyError, match=r"inputs changed while the grid ran \(models/artifacts/x.npz\)"):
        grid.run_grid(cells, ["straight"], cache_dir=tmp_path, workers=1, show_progress=False,
                      factory=retraining_factory)
    assert list((tmp_path / "runs").glob("*.json")) == []


@pytest.mark.slow
def test_the_quick_grid_runs_on_two_workers(tmp_path: Path) -> None:
    """``make robustness-smoke``: 2 controllers x 2 cells on spawned workers, then again
    from the cache."""
    argv = ["--quick", "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"),
            "--no-progress"]
    assert grid.main(argv) == 0
    with (tmp_path / "out" / "robustness.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and {r["controller"] for r in rows} == set(grid.QUICK_CONTROLLERS)
    assert len(list((tmp_path / "cache" / "runs").glob("*.json"))) == 4
    first = (tmp_path / "out" / "robustness.csv").read_text()
    assert grid.main(argv) == 0
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
    summary = grid.summarise(records, ["p", "q"])
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
    line = grid.ranking_line(summary)
    assert "over the 2 cells" in line and "p, q (1 of 2 each)" in line


def test_observer_line_counts_eso_dkmpc_against_dkmpc_overall_and_on_mismatch_cells() -> None:
    nominal, heavy, lagging, lost = (Cell("dlc", 0.85, 30.0, 0.0, 1.0), Cell("dlc", 0.85, 30.0, 300.0, 1.0),
                                     Cell("dlc", 0.5, 50.0, 0.0, 3.0), Cell("dlc", 0.3, 70.0, 300.0, 3.0))
    records = [_record("eso-dkmpc", nominal, 0.2), _record("dkmpc", nominal, 0.1),
               _record("eso-dkmpc", heavy, 0.1), _record("dkmpc", heavy, 0.2),
               _record("eso-dkmpc", lagging, 0.3), _record("dkmpc", lagging, None),
               _record("eso-dkmpc", lost, None), _record("dkmpc", lost, None)]  # neither: left out
    line = grid.observer_line(records)
    assert "below DKMPC's on 2 of 3 (DKMPC lower on 1)" in line
    assert "(mass +300 kg or steering lag x3) on 2 of 2 (DKMPC lower on 0)" in line
    assert grid.observer_line([_record("eso-dkmpc", nominal, 0.2)]) is None

"""The disturbance study (make disturbances): the straight-curve-straight path and its
scenario, the study's grids, the steady offsets on straights, and the engine end to end on
two cells (campaign runner, serial, then the report)."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from controller.reference import ReferencePath
from hil.path_files import (STRAIGHT_CURVE, STRAIGHT_CURVE_PATH_FILE, format_path_csv,
                            straight_curve_curvature, straight_curve_points)
from hil.scenario import load_scenario
from studies.campaign.executors import SerialExecutor
from studies.campaign.cell import run_cell
from studies.campaign.grid import HORIZON_ROOM_M, GridError, load_grid
from studies.campaign.runner import cached_rows, run_campaign
from studies.disturbance_offsets import (MIN_TIME_ON_S, WINDOW_S, label_straights, steady_offset,
                                         straight_sections)
from studies.disturbance_report import OUTPUT_NAMES, main as report_main, write_report

ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------- the path

def test_shipped_straight_curve_path_equals_the_regenerated_one():
    """Regenerate with: python -m hil.path_files --path straight_curve"""
    assert STRAIGHT_CURVE_PATH_FILE.read_text() == format_path_csv(straight_curve_points())


def test_the_path_is_straight_curve_straight():
    path = ReferencePath.from_csv(STRAIGHT_CURVE_PATH_FILE)
    layout = STRAIGHT_CURVE
    start = int(round(layout.lead_in_m / layout.step_m))
    assert (path.x[start], path.y[start], path.yaw[start]) == (0.0, 0.0, 0.0)
    assert path.yaw[-1] == pytest.approx(math.pi / 2, abs=1e-6)           # a 90 degree left turn
    assert path.s[-1] == pytest.approx((len(path.s) - 1) * layout.step_m, abs=1e-3)  # chords ~ the arc
    np.testing.assert_allclose(straight_curve_curvature(np.array([0.0, 80.0, 92.5, 105.0, 130.0, 183.6])),
                               [0.0, 0.0, 0.01, 0.02, 0.02, 0.0], atol=1e-12)
    sections = straight_sections(path.s, path.yaw)
    print(f"straights (m of arc): {[(round(a, 2), round(b, 2)) for a, b in sections]}; arc {layout.arc_m:.2f} m")
    assert len(sections) == 2
    assert sections[0] == pytest.approx((0.0, layout.curve_start_m), abs=0.5)
    assert sections[1] == pytest.approx((layout.curve_end_m, layout.length_m), abs=0.5)


def test_the_scenario_ends_on_the_final_straight_with_room_for_the_horizons():
    scenario = load_scenario("straight_curve")
    layout = STRAIGHT_CURVE
    end_of_run = layout.lead_in_m + scenario.start.speed_mps * scenario.duration_s
    print(f"the run ends at arc length {end_of_run:.1f} m; the final straight is "
          f"{layout.curve_end_m:.1f}-{layout.run_end_m:.1f} m, the path {layout.length_m:.1f} m")
    assert layout.curve_end_m + MIN_TIME_ON_S * scenario.start.speed_mps < end_of_run <= layout.run_end_m
    assert layout.length_m - end_of_run >= HORIZON_ROOM_M
    assert scenario.mu == 0.85 and scenario.start.speed_mps == pytest.approx(50 / 3.6)


# ---------------------------------------------------------------------------- the grids

def test_the_study_grid_has_every_controller_and_two_sizes_of_each_disturbance():
    from controller.registry import ALL_CONTROLLER_NAMES
    from models.disturbance import Disturbances

    grid = load_grid("disturbances")
    assert list(dict.fromkeys(c.controller for c in grid.cells)) == list(ALL_CONTROLLER_NAMES)
    assert {c.scenario for c in grid.cells} == {"dlc_high_mu", "straight_curve"}
    assert grid.keep_trace and {c.ecu for c in grid.cells} == {"python"}
    kinds: dict[str, int] = {}
    for name, table in grid.disturbances.items():
        if name == "none":
            continue
        parsed = Disturbances.from_mapping(table)
        assert parsed.any and parsed.start_s == 0.0
        kind = next(k for k in ("steer_offset_rad", "bank_angle_rad", "crosswind_force_n", "gust_force_n",
                                "yaw_rate_bias_rad_s", "pull_stiffness_scale") if k in table)
        kinds[kind] = kinds.get(kind, 0) + 1
    assert kinds == dict.fromkeys(kinds, 2) and len(kinds) == 6
    assert len(grid.cells) == len(ALL_CONTROLLER_NAMES) * 2 * 13
    smoke = load_grid("disturbances_smoke")
    assert len(smoke.cells) == 4 and smoke.keep_trace
    assert smoke.disturbances["offset 0.02 rad"] == grid.disturbances["offset 0.02 rad"]


def test_all_stands_alone_on_the_controller_axis(tmp_path):
    file = tmp_path / "g.toml"
    file.write_text('[axes]\ncontroller = ["all", "lmpc"]\nscenario = ["dlc_smoke"]\n')
    with pytest.raises(GridError, match="'all' stands alone"):
        load_grid(file)
    file.write_text('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\n[run]\nkeep_trace = 1\n')
    with pytest.raises(GridError, match="run.keep_trace = 1: must be true or false"):
        load_grid(file)


# ---------------------------------------------------------------------------- steady offsets

def _trace(times: np.ndarray, e_y: np.ndarray, speed: float = 10.0, start_m: float = 20.0) -> dict:
    return {"time_s": times.tolist(), "e_y": e_y.tolist(), "progress": (start_m + speed * times).tolist()}


def test_steady_offset_is_the_mean_over_the_last_window_on_the_straight():
    times = np.arange(0.0, 10.0 + 1e-9, 0.025)
    e_y = np.where(times <= 4.0 + 1e-9, 0.05, 0.02)  # 0.05 m up to s = 60 m, then 0.02 m
    trace = _trace(times, e_y)
    assert steady_offset(trace, 0.0, 60.0) == pytest.approx(0.05)        # window 2-4 s
    assert steady_offset(trace, 80.0, 200.0) == pytest.approx(0.02)      # the car is there 6-10 s
    assert steady_offset(trace, 0.0, 40.0) is None                       # only 2 s on it
    assert steady_offset(trace, 300.0, 400.0) is None                    # never reached
    ramp = _trace(times, times * 0.01)
    last = times[times >= 10.0 - WINDOW_S - 1e-9]
    assert steady_offset(ramp, 0.0, 200.0) == pytest.approx(float(np.mean(last * 0.01)))
    labels = label_straights([(0.0, 60.0), (80.0, 200.0), (250.0, 300.0)], [True, True, False])
    assert [s.label for s in labels] == ["first straight", "final straight"]


# ---------------------------------------------------------------------------- the engine

ENGINE_GRID = """
name = "engine"
[axes]
controller = ["lmpc"]
scenario = ["straight_curve"]
disturbance = ["none", "wind 800 N"]
[run]
keep_trace = true
[disturbances."wind 800 N"]
crosswind_force_n = 800.0
crosswind_cp_m = 0.6
"""


def test_the_engine_on_two_cells(tmp_path):
    """LMPC on the straight-curve-straight path without a disturbance and with an 800 N
    crosswind: the campaign runner (serially) and the report. LMPC has no integral action,
    so the wind leaves it a steady offset to the left on both straights; without it, none."""
    (tmp_path / "engine.toml").write_text(ENGINE_GRID)
    grid = load_grid(tmp_path / "engine.toml")
    result = run_campaign(grid, tmp_path / "campaign", SerialExecutor(run_cell), progress=False)
    assert [r["completed"] for r in result.rows] == [1, 1]
    for row in result.rows:
        trace = row["trace"]
        assert len(trace["time_s"]) == len(trace["e_y"]) == len(trace["progress"]) == 700
    assert cached_rows(grid, tmp_path / "campaign") == result.rows
    written = write_report(grid, result.rows, tmp_path / "report", command="test",
                           campaign_dir=tmp_path / "campaign")
    assert [p.name for p in written] == list(OUTPUT_NAMES) and all(p.stat().st_size for p in written)
    rows = list(csv.DictReader((tmp_path / "report" / "disturbances.csv").open()))
    offsets = {r["disturbance"]: (float(r["offset_first_straight"]), float(r["offset_final_straight"]))
               for r in rows}
    print("steady offsets (m) on the first and final straight:", offsets)
    assert all(abs(v) < 0.003 for v in offsets["none"])
    assert all(v > 0.005 for v in offsets["wind 800 N"])
    document = json.loads((tmp_path / "report" / "disturbances.json").read_text())
    assert [s["label"] for s in document["straights"]["straight_curve"]] == ["first straight", "final straight"]
    assert len(document["cells"]) == 2
    text = (tmp_path / "report" / "disturbances.md").read_text()
    print(text)
    assert "Steady lateral offset on the final straight" in text and "| wind 800 N |" in text
    # the command line on the same cache: the same report
    assert report_main(["engine", "--campaign", str(tmp_path / "campaign"), "--out", str(tmp_path / "cli")]) == 1
    assert report_main([str(tmp_path / "engine.toml"), "--campaign", str(tmp_path / "campaign"),
                        "--out", str(tmp_path / "cli")]) == 0
    assert (tmp_path / "cli" / "disturbances.csv").read_text() == (tmp_path / "report" / "disturbances.csv").read_text()


def test_the_report_refuses_a_folder_without_the_campaign(tmp_path, capsys):
    assert report_main(["disturbances_smoke", "--campaign", str(tmp_path / "nothing"), "--out", str(tmp_path)]) == 1
    assert "no campaign there" in capsys.readouterr().err
    (tmp_path / "empty" / "cache").mkdir(parents=True)
    assert report_main(["disturbances_smoke", "--campaign", str(tmp_path / "empty"), "--out", str(tmp_path)]) == 1
    assert "none of the 4 cells" in capsys.readouterr().err

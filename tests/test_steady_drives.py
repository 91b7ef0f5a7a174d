"""The observer tuning's steady drives (studies/steady_drives.py): committed files equal the
regenerated ones, they differ from every evaluation path, and each run ends on its final
straight."""
from __future__ import annotations

import numpy as np

from hil.path_files import straight_curve_points
from hil.scenario import list_scenarios, load_scenario
from studies.observer_tuning import TUNING_DISTURBANCES, disturbed_tuning_set
from studies.steady_drives import STEADY_DRIVES, scenario_text, steady_scenarios


def test_committed_steady_drives_equal_the_regenerated_ones() -> None:
    """Regenerate with: python -m studies.steady_drives."""
    for drive, scenario in zip(STEADY_DRIVES, steady_scenarios()):
        assert drive.scenario_file.read_text() == scenario_text(drive)
        stored, fresh = scenario.path_points(), straight_curve_points(drive.layout)
        assert stored.shape == fresh.shape and float(np.max(np.abs(stored - fresh))) < 2e-6


def test_the_steady_drives_are_no_evaluation_path_and_end_on_a_straight() -> None:
    evaluation = [load_scenario(name).path_points() for name in list_scenarios()]
    for drive, scenario in zip(STEADY_DRIVES, steady_scenarios()):
        points = scenario.path_points()
        assert all(points.shape != other.shape or not np.allclose(points, other) for other in evaluation)
        end_arc_m = drive.layout.lead_in_m + scenario.duration_s * drive.speed_kmh / 3.6
        assert drive.layout.curve_end_m + 0.5 * drive.layout.final_straight_m < end_arc_m < drive.layout.run_end_m


def test_every_tuning_run_has_its_disturbed_twin() -> None:
    scenarios = disturbed_tuning_set()
    names = [s.name for s in scenarios]
    assert len(names) == 22 and set(TUNING_DISTURBANCES) == {n for n in names if not n.endswith("+disturbed")}
    assert {f"{n}+disturbed" for n in TUNING_DISTURBANCES} <= set(names)

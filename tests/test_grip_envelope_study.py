"""The grip-envelope study (studies/grip_envelope.py): its runs and the plants they build,
the objective and the choice, and its report's lines. The envelope itself is tested with
the controllers (controller/grip_envelope.py); no closed-loop run here."""
from __future__ import annotations

import dataclasses
import math

import pytest

from hil.scenario import load_scenario
from studies import grip_envelope
from studies.campaign.closed_loop_cell import plant_for
from studies.identification import changed_params
from studies.tuning_sweep_executor import FAILURE_PENALTY_M, Evaluation, objective


def _evaluation(name: str, degrees: float | None, rmse: dict[str, float], completed: dict[str, bool],
                failure: dict[str, str | None] | None = None) -> Evaluation:
    setting = () if degrees is None else grip_envelope.setting(degrees)
    return Evaluation(controller=name, stage="grip", setting=setting, rmse_m=rmse,
                      max_abs_m={s: 3 * v for s, v in rmse.items()}, completed=completed,
                      failure=failure or {s: None if ok else "|e_Y| = 10.20 m > 10.0 m at t = 8.215 s (X = 90.0 m)"
                                          for s, ok in completed.items()},
                      objective_m=objective(rmse, completed), seconds=1.0)


def test_the_tuning_runs_and_their_plants() -> None:
    disturbed, limit = grip_envelope.tuning_scenarios()
    assert (len(disturbed), len(limit)) == (22, 22)
    assert [s.name for s in limit] == ([f"{s.name}@rear_x0.65" for s in disturbed[:11]]
                                       + [f"{s.name}@rear_x0.65+150kg+lag_x2" for s in disturbed[:11]])
    assert not any(s.name.endswith("+disturbed") for s in disturbed[:11])
    for scenario, original in zip(limit, disturbed[:11] * 2):
        params = original.vehicle_params()
        expected = dataclasses.replace(params, cornering_stiffness_rear_scale=params.cornering_stiffness_rear_scale * 0.65)
        plant = plant_for(scenario)[0]
        if "+150kg" in scenario.name:
            expected = dataclasses.replace(expected, mass=params.mass + 150.0,
                                           steer_time_constant=2.0 * params.steer_time_constant)
        assert plant.params == expected
    # the tuning set's own runs keep the nominal plant
    assert plant_for(disturbed[0])[0].params == disturbed[0].vehicle_params()


def test_the_evaluation_runs_on_the_nominal_and_the_changed_plant() -> None:
    scenarios = grip_envelope.evaluation_scenarios()
    assert [s.name for s in scenarios] == ["dlc_high_mu", "dlc_low_mu", "dlc_high_mu@changed", "dlc_low_mu@changed"]
    for scenario in scenarios[2:]:
        nominal = load_scenario(scenario.name.removesuffix("@changed"))
        assert plant_for(scenario)[0].params == changed_params(nominal.vehicle_params())
    assert plant_for(scenarios[1])[0].params == scenarios[1].vehicle_params()


def test_the_jobs() -> None:
    jobs = grip_envelope.tuning_jobs()
    assert len(jobs) == 6 * 6
    assert {name for name, _, _ in jobs} == {"eso-dkmpc", "dkmpc", "lmpc", "lmpc-eso", "dmdc-eso", "nmpc"}
    values = [dict(s)["grip_slip_excess"] for name, _, s in jobs if name == "nmpc"]
    assert values == pytest.approx([0.0] + [math.radians(d) for d in (2, 3, 4, 5, 6)])
    references = grip_envelope.evaluation_jobs()[len(jobs):]
    assert references == [("stanley", "reference", ())]


def test_the_objective_counts_a_lost_run_and_ties_go_to_off() -> None:
    runs = ["a", "b", "c"]
    off = _evaluation("dkmpc", 0.0, {"a": 0.02, "b": 0.04, "c": 0.03}, dict.fromkeys(runs, True))
    tied = _evaluation("dkmpc", 2.0, {"a": 0.03, "b": 0.03, "c": 0.03}, dict.fromkeys(runs, True))
    lost = _evaluation("dkmpc", 3.0, {"a": 0.01, "b": 0.01, "c": 0.5}, {"a": True, "b": True, "c": False})
    assert lost.objective_m == pytest.approx((0.02 + FAILURE_PENALTY_M) / 3)
    assert grip_envelope.subset_objective(lost, ["a", "b"]) == pytest.approx(0.01)
    assert grip_envelope.subset_objective(lost, ["c"]) == FAILURE_PENALTY_M
    assert off.objective_m == pytest.approx(tied.objective_m)
    assert grip_envelope.choices([off, tied, lost])["dkmpc"] is off
    lower = _evaluation("dkmpc", 4.0, {"a": 0.02, "b": 0.02, "c": 0.02}, dict.fromkeys(runs, True))
    assert grip_envelope.choices([off, tied, lost, lower])["dkmpc"] is lower


def test_the_report_lines() -> None:
    disturbed, limit = ["t1", "t2"], ["t1@rear_x0.65"]
    runs = disturbed + limit
    off = _evaluation("lmpc", 0.0, {"t1": 0.02, "t2": 0.04, "t1@rear_x0.65": 0.3},
                      {"t1": True, "t2": True, "t1@rear_x0.65": False})
    on = _evaluation("lmpc", 3.0, dict.fromkeys(runs, 0.03), dict.fromkeys(runs, True))
    lane = ["dlc_high_mu", "dlc_low_mu@changed"]
    study_off = _evaluation("lmpc", 0.0, {"dlc_high_mu": 0.02, "dlc_low_mu@changed": 2.0},
                            {"dlc_high_mu": True, "dlc_low_mu@changed": False})
    study_on = _evaluation("lmpc", 3.0, {"dlc_high_mu": 0.021, "dlc_low_mu@changed": 0.049}, dict.fromkeys(lane, True))
    stanley = _evaluation("stanley", None, {"dlc_high_mu": 0.016, "dlc_low_mu@changed": 0.2},
                          dict.fromkeys(lane, True))
    text, summary = grip_envelope.report([off, on], [study_off, study_on, stanley], disturbed, limit,
                                         command="python -m studies.grip_envelope", minutes=1.0)
    # off: (0.02 + 0.04 + 10) / 3; over the tuning set alone 0.03
    assert "| lmpc | off | 3353.33 | 30.00 | 10000.00 | 1 |  |" in text
    assert "| lmpc | 3 deg | 30.00 | 30.00 | 30.00 | 0 | **chosen** |" in text
    assert "- lmpc: 3 deg, 3353.33 -> 30.00\n" in text
    edge = _evaluation("lmpc", 6.0, dict.fromkeys(runs, 0.01), dict.fromkeys(runs, True))
    text_edge, _ = grip_envelope.report([off, on, edge], [], disturbed, limit, command="c", minutes=1.0)
    assert "- lmpc: 6 deg, 3353.33 -> 10.00 (the grid's largest value: a larger one was not run)" in text_edge
    assert "| lmpc | off | 0.020 | lost at 8.2 s | 6.000 |" in text
    assert "| lmpc | 3 deg (chosen) | 0.021 | 0.049 | 0.147 |" in text
    assert "| stanley | (no envelope) | 0.016 | 0.200 | 0.600 |" in text
    assert "by e_Y RMSE (completed runs first): lmpc 0.049, stanley 0.200." in text
    assert "Run with `--no-write`: the tuning file was left as it was." in text
    assert "## The refinement" not in text  # no rounds given
    assert summary["chosen_deg"] == {"lmpc": 3.0}
    assert summary["tuning"]["lmpc@0"]["objective_limit_m"] == FAILURE_PENALTY_M
    assert "seconds" not in summary["evaluation"]["stanley@-"]


def test_the_figure_shows_off_three_degrees_and_the_chosen_setting() -> None:
    four = grip_envelope.setting(4.0)
    refined = grip_envelope.setting(3.0) + (("grip_margin", 0.2),)
    assert grip_envelope.figure_settings("dkmpc", {"dkmpc": four}) == [
        grip_envelope.setting(0.0), grip_envelope.setting(3.0), four]
    assert grip_envelope.figure_settings("lmpc", {"lmpc": grip_envelope.setting(3.0)}) == [
        grip_envelope.setting(0.0), grip_envelope.setting(3.0)]
    assert grip_envelope.figure_settings("nmpc", {"nmpc": grip_envelope.setting(0.0)}) == [
        grip_envelope.setting(0.0), grip_envelope.setting(3.0)]
    assert grip_envelope.figure_settings("lmpc", {"lmpc": refined})[-1] == refined
    assert grip_envelope.setting_label(refined) == "3 deg, margin 0.2"
    assert grip_envelope.setting_label(grip_envelope.setting(0.0) + (("grip_peak_time", 0.5),)) == "off, peak time 0.5"


def _refine_with(objectives: dict[tuple[str, str, float], float]) -> tuple[list, dict, list]:
    """The refinement of dkmpc (on at 4 deg) and nmpc (off), every job's objective looked up
    in ``objectives`` by (controller, field, value) (else 0.05 m); the jobs run, in order."""
    runs = ["a"]
    stage_one = {"dkmpc": _evaluation("dkmpc", 4.0, {"a": 0.04}, {"a": True}),
                 "nmpc": _evaluation("nmpc", 0.0, {"a": 0.03}, {"a": True})}
    ran: list = []

    def run(jobs):
        ran.extend(jobs)
        out = []
        for name, stage, setting in jobs:
            field, value = setting[-1]
            e = _evaluation(name, 4.0, dict.fromkeys(runs, objectives.get((name, field, value), 0.05)),
                            dict.fromkeys(runs, True))
            out.append(dataclasses.replace(e, stage=stage, setting=setting))
        return out

    rounds, final = grip_envelope.refine(stage_one, run)
    return rounds, final, ran


def test_the_refinement_moves_one_field_at_a_time_and_ties_keep_the_incumbent() -> None:
    rounds, final, ran = _refine_with({("dkmpc", "grip_margin", 0.2): 0.03, ("dkmpc", "grip_recovery", 5.0): 0.04})
    # only the controller that is on; the incumbent's (the default's) runs are not repeated
    assert {name for name, _, _ in ran} == {"dkmpc"}
    assert len(ran) == sum(len(values) - 1 for _, values in grip_envelope.REFINE_AXES) == 3 + 5 + 5
    assert [field for field, _ in rounds] == ["grip_margin", "grip_recovery", "grip_peak_time"]
    # the margin moved to 0.2 (lower); the recovery's 5.0 (0.04 m) is worse than the choice so far (0.03 m)
    assert dict(final["dkmpc"].setting) == {"grip_slip_excess": math.radians(4.0), "grip_margin": 0.2}
    # the later rounds start from the choice so far
    assert [dict(s)["grip_margin"] for _, _, s in ran[:3]] == [0.0, 0.05, 0.2]
    assert all(dict(s)["grip_margin"] == 0.2 for _, _, s in ran[3:])
    assert final["nmpc"].setting == grip_envelope.setting(0.0)
    first, compared = rounds[0]
    assert [e.objective_m for e in compared["dkmpc"]] == pytest.approx([0.04, 0.05, 0.05, 0.03])
    summary: dict = {}
    lines = grip_envelope.refinement_lines(rounds, final, summary)
    assert "| dkmpc | grip_margin | 4 deg, margin 0.2 | 30.00 | 0 | **chosen** |" in lines
    assert "| dkmpc | grip_margin | 4 deg | 40.00 | 0 |  |" in lines
    assert summary["chosen"] == {"dkmpc": "4 deg, margin 0.2", "nmpc": "off"}
    # 0.2 is the margin grid's largest value: the report says a larger one was not run
    assert summary["grid_edges"] == {"dkmpc": {"grip_margin": 0.2}}
    assert "- dkmpc: margin 0.2 (the grid's largest value: a larger one was not run)" in lines
    _, tie = _refine_with({("dkmpc", "grip_margin", 0.05): 0.04})[:2]
    assert tie["dkmpc"].setting == grip_envelope.setting(4.0)  # a tie keeps the incumbent


def test_the_written_fields_and_the_tuning_file_takes_them() -> None:
    from controller.tuning import DEFAULT_TUNING_PATH
    from studies.tuning_file import update_tuning_text

    _, final, _ = _refine_with({("dkmpc", "grip_margin", 0.2): 0.03})
    defaults = grip_envelope.GRIP_DEFAULTS
    written = grip_envelope.written_settings(final)
    # the fields the choice does not name go in at their defaults, where the stage ran them
    assert written["dkmpc"] == (("grip_slip_excess", math.radians(4.0)), ("grip_margin", 0.2),
                                ("grip_recovery", defaults["grip_recovery"]),
                                ("grip_peak_time", defaults["grip_peak_time"]))
    assert dict(written["nmpc"])["grip_slip_excess"] == 0.0
    # every MPC table of the shipped file has the four fields in place
    text = DEFAULT_TUNING_PATH.read_text(encoding="utf-8")
    every = {name: tuple((f, 0.0 if f == "grip_slip_excess" else defaults[f])
                         for f in grip_envelope.WRITTEN_FIELDS) for name in grip_envelope.ENVELOPE_CONTROLLERS}
    updated = update_tuning_text(text, {**every, **written}, comment=grip_envelope.TUNING_COMMENT)
    assert updated.count(grip_envelope.TUNING_COMMENT) == len(grip_envelope.ENVELOPE_CONTROLLERS)
    jobs = grip_envelope.evaluation_jobs(final)
    assert ("dkmpc", "grip", final["dkmpc"].setting) in jobs
    assert len(jobs) == len(grip_envelope.evaluation_jobs()) + 1  # nmpc's choice is among the tuning jobs


def test_a_run_that_failed_otherwise_is_named_so() -> None:
    e = _evaluation("dkmpc", 0.0, {"x": 0.5}, {"x": False}, {"x": "plant state not finite at t = 3.250 s"})
    assert grip_envelope.outcome(e, "x") == "failed at 3.2 s"


def test_cli_refuses_no_workers(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        grip_envelope.main(["--workers", "0", "--out", "/nonexistent/never-written"])
    assert "--workers must be >= 1" in capsys.readouterr().err


def test_the_margin_can_go_to_zero_and_zero_is_no_grid_edge() -> None:
    _, final, _ = _refine_with({("dkmpc", "grip_margin", 0.0): 0.02})
    assert dict(final["dkmpc"].setting)["grip_margin"] == 0.0
    assert grip_envelope.grid_edge("grip_margin", 0.0) == ""  # the field's own bound
    assert "smallest" in grip_envelope.grid_edge("grip_recovery", 5.0)
    assert "largest" in grip_envelope.grid_edge("grip_peak_time", 16.0)
    assert grip_envelope.grid_edge("grip_peak_time", 4.0) == ""
    assert grip_envelope.grid_edge("grip_recovery", 10.0) == ""


def test_the_stage_starts_from_the_defaults_not_from_its_own_earlier_choice() -> None:
    """A second run must choose what the first did: the refined fields start from the
    tuning tables' defaults whatever the tuning file holds, every other field as the file."""
    from controller.tuning import load_tuning

    shipped = load_tuning()
    moved = shipped
    for name in grip_envelope.ENVELOPE_CONTROLLERS:
        moved = grip_envelope.with_setting(moved, name, (("grip_margin", 0.5), ("grip_recovery", 33.0),
                                                         ("grip_peak_time", 3.0)))
    for tuning in (shipped, moved):
        start = grip_envelope.starting_tuning(tuning)
        for name in grip_envelope.ENVELOPE_CONTROLLERS:
            table = start.for_controller(name)
            for field, default in grip_envelope.GRIP_DEFAULTS.items():
                assert getattr(table, field) == default
            assert table.grip_slip_excess == shipped.for_controller(name).grip_slip_excess
            assert table.q_yaw == shipped.for_controller(name).q_yaw
    assert grip_envelope.starting_tuning(shipped) == grip_envelope.starting_tuning(moved)

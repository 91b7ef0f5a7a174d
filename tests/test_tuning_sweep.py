"""The tuning set and the tuning sweep (``make tune``): properties only.

The tuning scenarios share nothing with the evaluation (names, path files, paths); the
sweep is one procedure for every registered controller; it picks the setting with the
lowest objective, counts incomplete runs as the penalty, is deterministic, and edits only
the swept values of the tuning file. No test here compares controllers with each other.
"""
from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from controller.registry import CONTROLLERS, GEOMETRIC_NAMES, MPC_NAMES
from controller.tuning import DEFAULT_TUNING_PATH, load_tuning, parse_tuning
from hil.errors import ScenarioError, StudyError
from hil.scenario import Scenario, list_scenarios, load_scenario
from studies import tuning_sweep
from studies.tuning_set import (POINT_SPACING_M, TUNING_SET, path_points, scenario_text,
                                tuning_scenarios)
from controller.tuning import StanleyTuning
from studies.tuning_sweep import (FAILURE_PENALTY_M, OBSERVER_FIELDS, OBSERVER_GRID,
                                  OBSERVER_START, STANLEY_GRID, WEIGHT_FIELDS, WEIGHT_GRID, SweepGrid,
                                  run_sweep, stage_one_grid, stage_one_settings, stage_two_settings,
                                  swept_fields, update_tuning_text)

ROOT = Path(__file__).resolve().parent.parent


def _evaluation_scenarios() -> list[Scenario]:
    """Every scenario an evaluation study runs: Tables II / III over CAN and without, and
    every shipped scenario of hil/scenarios/*.toml."""
    from studies import paper_tables, run_all

    names = set(paper_tables.SCENARIOS) | set(run_all.SCENARIOS) | set(list_scenarios())
    return [load_scenario(name) for name in sorted(names)]


# ---------------------------------------------------------------------------- tuning set

def test_tuning_set_is_disjoint_from_the_evaluation() -> None:
    tuning = tuning_scenarios()
    evaluation = _evaluation_scenarios()
    assert {"dlc_high_mu", "dlc_low_mu"} <= {s.name for s in evaluation}
    assert not {s.name for s in tuning} & {s.name for s in evaluation}
    assert not {s.path_file.resolve() for s in tuning} & {s.path_file.resolve() for s in evaluation}
    assert not {s.source for s in tuning} & {s.source for s in evaluation}
    assert not {s.name for s in tuning} & set(list_scenarios())  # not listed as shipped ones
    evaluation_paths = [s.path_points() for s in evaluation]
    for scenario in tuning:  # not a copy of an evaluation path under another name
        points = scenario.path_points()
        assert all(points.shape != other.shape or not np.allclose(points, other)
                   for other in evaluation_paths), scenario.name


def test_committed_tuning_set_equals_the_regenerated_one() -> None:
    """Regenerate with: python -m studies.tuning_set (make tuning-set)."""
    for manoeuvre in TUNING_SET:
        committed = Scenario.load(manoeuvre.scenario_file)
        assert manoeuvre.scenario_file.read_text() == scenario_text(manoeuvre)
        stored = committed.path_points()
        fresh = path_points(manoeuvre)
        difference = float(np.max(np.abs(stored - fresh)))
        print(f"{manoeuvre.name}: max |committed - regenerated| = {difference:.2e}")
        assert stored.shape == fresh.shape and difference < 2e-6


def test_tuning_scenarios_start_on_a_smooth_path_at_speed() -> None:
    for manoeuvre, scenario in zip(TUNING_SET, tuning_scenarios()):
        points = scenario.path_points()
        at_start = np.flatnonzero(np.hypot(points[:, 0], points[:, 1]) < 1e-9)
        assert at_start.size == 1 and points[at_start[0], 2] == pytest.approx(0.0, abs=1e-9)
        assert scenario.start.speed_mps == pytest.approx(manoeuvre.speeds_kmh[0] / 3.6)
        assert 10.0 <= scenario.duration_s <= 15.0 and scenario.mu == manoeuvre.mu
        heading_change = np.abs(np.diff(np.unwrap(points[:, 2])))
        assert np.max(heading_change) / POINT_SPACING_M < 0.05  # curvature below 1/20 m
        driven = manoeuvre.max_speed_mps * scenario.duration_s
        ahead = points[at_start[0]:]
        assert np.sum(np.hypot(np.diff(ahead[:, 0]), np.diff(ahead[:, 1]))) > driven + 30.0


def test_unknown_tuning_scenario_is_refused() -> None:
    with pytest.raises(ScenarioError, match="dlc_high_mu"):
        tuning_scenarios(["dlc_high_mu"])


# ---------------------------------------------------------------------------- procedure

def test_the_procedure_is_the_same_for_every_registered_controller() -> None:
    tuning = load_tuning()

    def part(setting, fields):
        return tuple((name, value) for name, value in setting if name in fields)

    assert set(MPC_NAMES) | set(GEOMETRIC_NAMES) == set(CONTROLLERS)
    for name in GEOMETRIC_NAMES:  # no MPC weights: its own stage-1 grid, nothing after it
        table = tuning.for_controller(name)
        assert swept_fields(table) == (STANLEY_GRID.fields, ())
        assert stage_one_grid(table) is STANLEY_GRID
        assert stage_one_settings((), stage_one_grid(table)) == STANLEY_GRID.settings()
        assert not tuning_sweep.has_low_speed_weights(table)
    stage_one = {}
    for name in MPC_NAMES:
        assert stage_one_grid(tuning.for_controller(name)) is WEIGHT_GRID
        weight_fields, observer_fields = swept_fields(tuning.for_controller(name))
        assert weight_fields == WEIGHT_FIELDS
        assert observer_fields in ((), OBSERVER_FIELDS), name
        settings = stage_one_settings(observer_fields)
        assert len(settings) == len(WEIGHT_GRID)
        assert all(part(s, OBSERVER_FIELDS) == part(OBSERVER_START, observer_fields) for s in settings)
        stage_one[name] = [part(s, WEIGHT_FIELDS) for s in settings]
        second = stage_two_settings(settings[-1], observer_fields)
        assert len(second) == (len(OBSERVER_GRID) if observer_fields else 0)
        assert all(part(s, WEIGHT_FIELDS) == stage_one[name][-1] for s in second)
        assert [part(s, OBSERVER_FIELDS) for s in second] == OBSERVER_GRID.restricted(observer_fields).settings()
    first = next(iter(stage_one.values()))
    assert all(weights == first for weights in stage_one.values())  # the same grid, same order


def test_every_grid_setting_is_a_valid_tuning_file() -> None:
    """Written into the real tuning file and validated by controller.tuning's own rules."""
    text = DEFAULT_TUNING_PATH.read_text()
    observed = [name for name in CONTROLLERS if swept_fields(load_tuning().for_controller(name))[1]]
    for weights in WEIGHT_GRID.settings():
        chosen = {name: weights for name in MPC_NAMES}
        parse_tuning(tomllib.loads(update_tuning_text(text, chosen)))
    for gains in STANLEY_GRID.settings():
        parse_tuning(tomllib.loads(update_tuning_text(text, {"stanley": gains})))
    for observer in OBSERVER_GRID.settings():
        chosen = {name: observer for name in observed}
        parse_tuning(tomllib.loads(update_tuning_text(text, chosen)))


def test_grid_refuses_repeated_levels() -> None:
    with pytest.raises(StudyError, match="distinct"):
        SweepGrid((("q_yaw", (1.0, 1.0)),))
    assert len(SweepGrid((("a", (1.0, 2.0)), ("b", (3.0,))))) == 2


# ---------------------------------------------------------------------------- tuning file

def test_tuning_file_edit_changes_only_the_swept_values() -> None:
    # The shipped file without the comments of an earlier sweep.
    text = "".join(line for line in DEFAULT_TUNING_PATH.read_text().splitlines(keepends=True)
                   if not line.rstrip().endswith(tuning_sweep.TUNING_COMMENT))
    chosen = {"lmpc": (("q_position", 300.0), ("q_yaw", 5.0), ("r_steer", 0.3), ("p_steer_rate", 300.0))}
    edited = update_tuning_text(text, chosen)
    before, after = text.splitlines(), edited.splitlines()
    assert len(after) == len(before) + 1  # one comment line under [lmpc]
    header = before.index("[lmpc]")
    assert after[header + 1].startswith("# q_position, q_yaw, r_steer, p_steer_rate: ")
    assert after[header + 1].endswith(tuning_sweep.TUNING_COMMENT)
    changed = [(b, a) for b, a in zip(before, after[:header + 1] + after[header + 2:]) if b != a]
    assert {a.split("=")[0].strip() for _, a in changed} <= {"q_position", "q_yaw", "r_steer"}
    document, original = tomllib.loads(edited), tomllib.loads(text)
    assert document["lmpc"]["q_position"] == 300.0 and document["lmpc"]["r_steer"] == 0.3
    assert {k: v for k, v in document.items() if k != "lmpc"} == {k: v for k, v in original.items() if k != "lmpc"}
    # A second sweep replaces its comment instead of adding another.
    again = update_tuning_text(edited, {"lmpc": (("q_position", 30.0),)})
    assert again.count(tuning_sweep.TUNING_COMMENT) == 1
    assert tomllib.loads(again)["lmpc"]["q_position"] == 30.0


def test_tuning_file_edit_keeps_trailing_comments() -> None:
    text = "[a]  # table note\nx = 1.0     # the x\ny = 2.0\n\n[b]\nx = 5.0\n"
    edited = update_tuning_text(text, {"a": (("x", 1000.0), ("y", 0.25))}, comment="note")
    assert "x = 1000.0  # the x\n" in edited and "y = 0.25\n" in edited
    assert edited.endswith("[b]\nx = 5.0\n") and edited.startswith("[a]  # table note\n# x, y: note\n")
    with pytest.raises(StudyError, match=r"\[c\]"):
        update_tuning_text(text, {"c": (("x", 1.0),)})
    with pytest.raises(StudyError, match="z"):
        update_tuning_text(text, {"b": (("z", 1.0),)})


# ---------------------------------------------------------------------------- the sweep

def _fake_result(rmse: float, completed: bool = True) -> SimpleNamespace:
    lateral = SimpleNamespace(rmse=rmse, max_abs=2.0 * rmse)
    return SimpleNamespace(completed=completed, failure=None if completed else "left the road",
                           tracking=SimpleNamespace(lateral=lateral))


def _scenario(name: str) -> SimpleNamespace:
    return SimpleNamespace(name=name)


#: No stage 4 (the tests of stages 1-3 check their exact evaluation lists).
NO_LOW_SPEED = SweepGrid(())
#: Small grids of the stand-in runner tests.
STAND_IN_WEIGHTS = SweepGrid((("q_position", (30.0, 100.0, 1000.0)), ("q_yaw", (20.0,)),
                              ("r_steer", (1.0,)), ("p_steer_rate", (300.0,))))
STAND_IN_OBSERVER = SweepGrid((("eso_pole", (0.0, 0.3)), ("eso_second_pole", (0.97,)),
                               ("disturbance_decay", (1.0,))))


def test_sweep_picks_the_lowest_objective_and_penalises_incomplete_runs() -> None:
    """On a stand-in runner (no plant): the objective is q_position's distance from 100,
    except that q_position 1000 leaves the road on one scenario, and the file's setting
    (q_position 10, off the grid) is the best of all but is no candidate."""
    tuning = load_tuning()
    tuning = dataclasses.replace(tuning, lmpc=dataclasses.replace(tuning.lmpc, q_position=10.0))
    weights, observer = STAND_IN_WEIGHTS, STAND_IN_OBSERVER

    def runner(scenario, controller):
        table = controller.tuning
        if table.q_position == 10.0:
            return _fake_result(1e-4)
        base = abs(np.log10(table.q_position / 100.0)) + 0.01
        if table.q_position == 1000.0 and scenario.name == "b":
            return _fake_result(0.001, completed=False)
        if hasattr(table, "eso_pole"):
            base += 0.002 * (table.eso_pole == 0.3)
        return _fake_result(base)

    sweeps = run_sweep(["lmpc", "lmpc-eso"], [_scenario("a"), _scenario("b")], tuning,
                       weight_grid=weights, observer_grid=observer,
                       observer_start=(("eso_pole", 0.3), ("eso_second_pole", 0.97), ("disturbance_decay", 1.0)),
                       runner=runner, show_progress=False, low_speed_grid=NO_LOW_SPEED, evaluate_before=True)
    lmpc, lmpc_eso = sweeps
    assert dict(lmpc.chosen.setting)["q_position"] == 100.0
    assert lmpc.chosen.objective_m == pytest.approx(0.01)
    failed = next(e for e in lmpc.evaluations if dict(e.setting)["q_position"] == 1000.0)
    assert failed.objective_m == pytest.approx((1.01 + FAILURE_PENALTY_M) / 2)
    assert [e.stage for e in lmpc.evaluations] == ["weights"] * 3  # no observer: no stage 2
    assert lmpc.before is not None and dict(lmpc.before.setting)["q_position"] == 10.0
    assert lmpc.before.objective_m < lmpc.chosen.objective_m  # reported, never chosen
    assert {e.stage for e in lmpc_eso.evaluations} == {"weights", "observer"}
    # Stage 2's point at OBSERVER_START is not rerun; the alternation's weight round at
    # eso_pole 0 adds the two q_position levels not yet run there, its observer round none.
    assert len(lmpc_eso.evaluations) == 3 + 1 + 2
    assert dict(lmpc_eso.chosen.setting) == {"q_position": 100.0, "q_yaw": 20.0, "r_steer": 1.0,
                                              "p_steer_rate": 300.0, "eso_pole": 0.0,
                                              "eso_second_pole": 0.97, "disturbance_decay": 1.0}
    assert [e.objective_m for e in lmpc.top(2)] == sorted(e.objective_m for e in lmpc.evaluations)[:2]


def test_alternation_leaves_the_basin_of_the_observer_start() -> None:
    """Stand-in runner where the best q_position depends on the observer: 30 at eso_pole 0.3
    (the start), 1000 at eso_pole 0. Stages 1-2 alone stop at q_position 30 / eso_pole 0;
    the alternation's weight round at eso_pole 0 finds q_position 1000, then stays."""
    tuning = load_tuning()
    weights, observer = STAND_IN_WEIGHTS, STAND_IN_OBSERVER

    def runner(scenario, controller):
        table = controller.tuning
        if table.eso_pole == 0.3:
            return _fake_result(0.1 + 0.1 * abs(np.log10(table.q_position / 30.0)))
        return _fake_result(0.02 * abs(np.log10(table.q_position / 1000.0)))

    (sweep,) = run_sweep(["lmpc-eso"], [_scenario("a")], tuning, weight_grid=weights,
                         observer_grid=observer,
                         observer_start=(("eso_pole", 0.3), ("eso_second_pole", 0.97), ("disturbance_decay", 1.0)),
                         runner=runner, show_progress=False, low_speed_grid=NO_LOW_SPEED)
    assert dict(sweep.chosen.setting)["q_position"] == 1000.0
    assert dict(sweep.chosen.setting)["eso_pole"] == 0.0
    assert sweep.chosen.objective_m == pytest.approx(0.0)
    stages = [e.stage for e in sweep.evaluations]
    assert stages == ["weights"] * 3 + ["observer"] + ["weights"] * 2  # then nothing new to run
    assert len({e.setting for e in sweep.evaluations}) == len(sweep.evaluations)  # none run twice
    # A second start at eso_pole 0 finds it in stage 1; nothing is left to alternate over.
    (started,) = run_sweep(["lmpc-eso"], [_scenario("a")], tuning, weight_grid=weights,
                           observer_grid=observer,
                           observer_start=(("eso_pole", 0.3), ("eso_second_pole", 0.97), ("disturbance_decay", 1.0)),
                           runner=runner, show_progress=False, low_speed_grid=NO_LOW_SPEED,
                           extra_observer_starts=((("eso_pole", 0.0), ("eso_second_pole", 0.97),
                                                   ("disturbance_decay", 1.0)),))
    assert [e.stage for e in started.evaluations] == ["weights"] * 6
    assert started.chosen.setting == sweep.chosen.setting


def test_report_rebuilds_from_the_stored_document(tmp_path: Path) -> None:
    """--report-from: the JSON document holds everything the report and figure need."""
    import json

    tuning = load_tuning()
    weights = SweepGrid((("q_position", (10.0, 100.0, 1000.0)), ("q_yaw", (20.0,)),
                         ("r_steer", (1.0,)), ("p_steer_rate", (300.0,))))

    def runner(scenario, controller):
        return _fake_result(0.01 * controller.tuning.q_position ** 0.5, completed=controller.tuning.q_position < 500)

    sweeps = run_sweep(["lmpc"], [_scenario("a")], tuning, weight_grid=weights, runner=runner,
                       show_progress=False, low_speed_grid=NO_LOW_SPEED, evaluate_before=True)
    context = {"Koopman artefact used": "none"}
    markdown = tuning_sweep.sweep_markdown(sweeps, ["a"], context, weights)
    document = json.loads(json.dumps(tuning_sweep.sweep_document(sweeps, ["a"], context, weights)))
    (tmp_path / "in.json").write_text(json.dumps(document))
    assert tuning_sweep.main(["--report-from", str(tmp_path / "in.json"), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "tuning_sweep.md").read_text() == markdown
    assert (tmp_path / "out" / "tuning_sweep.png").stat().st_size > 0
    assert "q_position 10" in markdown.split("#### lmpc")[1].split("\n| 1 |")[1].splitlines()[0]


def _stored_lmpc_dkmpc_sweep(tmp_path: Path) -> tuple[Path, list]:
    """A stand-in sweep of LMPC and DKMPC on scenario "a", stored as a sweep document
    recording the Koopman artefact "dk_d5.npz sha256 aaaaaaaaaaaa": (its path, the sweeps)."""
    import json

    weights = SweepGrid((("q_position", (10.0, 100.0)), ("q_yaw", (20.0,)), ("r_steer", (1.0,)),
                         ("p_steer_rate", (300.0,))))
    sweeps = run_sweep(["lmpc", "dkmpc"], [_scenario("a")], load_tuning(), weight_grid=weights,
                       runner=lambda scenario, controller: _fake_result(0.01), show_progress=False,
                       low_speed_grid=NO_LOW_SPEED)
    context = {"Koopman artefact used": "dk_d5.npz sha256 aaaaaaaaaaaa"}
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps(tuning_sweep.sweep_document(sweeps, ["a"], context, weights)))
    return path, sweeps


def test_reuse_of_another_artefact_reruns_the_koopman_controllers(tmp_path: Path) -> None:
    """--reuse of a sweep on another Koopman artefact keeps the physics-model controllers'
    evaluations and leaves out those of the controllers on the Koopman model."""
    path, _ = _stored_lmpc_dkmpc_sweep(tmp_path)
    same = tuning_sweep.reusable_evaluations(path, ["a"], {"Koopman artefact used": "dk_d5.npz sha256 aaaaaaaaaaaa"})
    other = tuning_sweep.reusable_evaluations(path, ["a"], {"Koopman artefact used": "dk_d5.npz sha256 bbbbbbbbbbbb"})
    assert {name for name, _ in same} == {"lmpc", "dkmpc"}
    assert {name for name, _ in other} == {"lmpc"}
    assert {k: v.objective_m for k, v in other.items()} == {k: v.objective_m for k, v in same.items() if k[0] == "lmpc"}
    assert "dkmpc" in tuning_sweep.KOOPMAN_CONTROLLERS and "lmpc" not in tuning_sweep.KOOPMAN_CONTROLLERS
    # A model file the stored sweep did not record (the DMDc model here) reruns only its users.
    unrecorded = tuning_sweep.reusable_evaluations(path, ["a"], {"Koopman artefact used": "dk_d5.npz sha256 aaaaaaaaaaaa",
                                                                 "DMDc artefact used": "dmdc.npz sha256 cccccccccccc"})
    assert unrecorded.keys() == same.keys()
    with pytest.raises(StudyError, match="scenarios"):
        tuning_sweep.reusable_evaluations(path, ["b"], {"Koopman artefact used": "dk_d5.npz sha256 aaaaaaaaaaaa"})


def test_sweep_records_a_controller_that_cannot_be_built() -> None:
    tuning = load_tuning()
    weights = SweepGrid((("q_position", (10.0,)), ("q_yaw", (20.0,)), ("r_steer", (1.0,)),
                         ("p_steer_rate", (300.0,))))

    def runner(scenario, controller):
        raise RuntimeError("solver exploded")

    [sweep] = run_sweep(["lmpc"], [_scenario("a")], tuning, weight_grid=weights,
                        runner=runner, show_progress=False, low_speed_grid=NO_LOW_SPEED)
    assert sweep.chosen.objective_m == FAILURE_PENALTY_M
    assert "solver exploded" in sweep.chosen.failure["a"]


def _short_tuning_scenario(folder: Path, duration_s: float = 2.0) -> Scenario:
    """Tuning scenario 3 cut to ``duration_s``, as a file in ``folder`` (the sweep's runs are
    campaign cells: they run scenario files)."""
    manoeuvre = TUNING_SET[3]
    document = tomllib.loads(manoeuvre.scenario_file.read_text())
    document["duration_s"] = duration_s
    document["path"]["file"] = str(manoeuvre.path_file.resolve())
    from studies.campaign.toml_text import to_toml

    file = folder / f"{manoeuvre.name}_{duration_s:g}s.toml"
    file.write_text(to_toml(document))
    return Scenario.load(file)


def test_tiny_real_sweep_returns_the_better_setting_and_repeats_exactly(tmp_path: Path) -> None:
    """LMPC on 2 s of one tuning scenario, two settings, in this process, twice (campaign
    cells, no cache between the two)."""
    tuning = load_tuning()
    weights = SweepGrid((("q_position", (30.0, 1000.0)), ("q_yaw", (20.0,)), ("r_steer", (1.0,)),
                         ("p_steer_rate", (300.0,))))
    scenario = _short_tuning_scenario(tmp_path)
    runs = [run_sweep(["lmpc"], [scenario], tuning, weight_grid=weights, show_progress=False, low_speed_grid=NO_LOW_SPEED)[0]
            for _ in range(2)]
    objectives = [[e.objective_m for e in sweep.evaluations] for sweep in runs]
    print(f"objectives {objectives[0]}")
    assert objectives[0] == objectives[1]  # bit for bit
    assert all(np.isfinite(objectives[0])) and objectives[0][0] != objectives[0][1]
    assert runs[0].chosen.objective_m == min(objectives[0])
    assert runs[0].chosen.setting == runs[1].chosen.setting


@pytest.mark.slow
def test_two_workers_give_the_same_sweep_as_one(tmp_path: Path) -> None:
    tuning = load_tuning()
    weights = SweepGrid((("q_position", (30.0, 300.0)), ("q_yaw", (5.0, 20.0)), ("r_steer", (1.0,)),
                         ("p_steer_rate", (300.0,))))
    scenario = _short_tuning_scenario(tmp_path, 1.0)
    serial, parallel = (run_sweep(["lmpc", "lmpc-eso"], [scenario], tuning, weight_grid=weights,
                                  observer_grid=SweepGrid((("eso_pole", (0.0, 0.3)),)),
                                  workers=workers, show_progress=False, low_speed_grid=NO_LOW_SPEED) for workers in (1, 2))
    for one, two in zip(serial, parallel):
        assert [(e.setting, e.objective_m) for e in one.evaluations] == \
            [(e.setting, e.objective_m) for e in two.evaluations]
        assert one.chosen.setting == two.chosen.setting


def test_cli_names_a_bad_scenario_and_writes_nothing(tmp_path: Path, capsys) -> None:
    tuning_copy = tmp_path / "tuning.toml"
    tuning_copy.write_text(DEFAULT_TUNING_PATH.read_text())
    out = tmp_path / "out"
    status = tuning_sweep.main(["--scenarios", "no_such_road", "--out", str(out), "--tuning",
                                str(tuning_copy), "--no-progress"])
    assert status == 1 and "no_such_road" in capsys.readouterr().err
    assert not out.exists() and tuning_copy.read_text() == DEFAULT_TUNING_PATH.read_text()


def test_low_speed_stage_schedules_the_weights_below_the_low_knot() -> None:
    """Stand-in runner: scenario "slow" is best at q_position 1000, "fast" at 30, and the
    runner sees the weights the controller uses at each scenario's speed (weights_at). One
    weighting must trade the two; stage 4 gives the slow one its own weights, and the
    setting is written with its low-speed fields."""
    tuning = load_tuning()
    speeds = {"slow": 8.0, "fast": 25.0}  # m/s: below and above weight_schedule_speeds
    best_q = {"slow": 1000.0, "fast": 30.0}

    def runner(scenario, controller):
        q = controller.tuning.weights_at(speeds[scenario.name]).q_position
        return _fake_result(0.01 + 0.01 * abs(np.log10(q / best_q[scenario.name])))

    low_speed = SweepGrid((("low_speed_q_position", (30.0, 100.0, 1000.0)), ("low_speed_q_yaw", (20.0,)),
                           ("low_speed_r_steer", (1.0,))))
    (sweep,) = run_sweep(["lmpc"], [_scenario("slow"), _scenario("fast")], tuning,
                         weight_grid=STAND_IN_WEIGHTS, runner=runner, show_progress=False,
                         low_speed_grid=low_speed)
    stages = [e.stage for e in sweep.evaluations]
    # The flat schedule at the best weights (q_position 30 everywhere) is not run again.
    assert stages == ["weights"] * 3 + ["low-speed"] * 2
    chosen = dict(sweep.chosen.setting)
    assert chosen["q_position"] == 30.0 and chosen["low_speed_q_position"] == 1000.0
    assert sweep.chosen.objective_m == pytest.approx(0.01)
    flat_best = min(e.objective_m for e in sweep.evaluations if e.stage == "weights")
    assert flat_best > sweep.chosen.objective_m
    written = dict(tuning_sweep.with_low_speed_weights(sweep.chosen.setting))
    assert written["low_speed_q_yaw"] == written["q_yaw"] == 20.0
    # A stage-1 setting writes a flat schedule.
    assert dict(tuning_sweep.with_low_speed_weights((("q_position", 3.0),)))["low_speed_q_position"] == 3.0


def test_reuse_takes_stored_evaluations_and_runs_only_the_rest() -> None:
    """--reuse: a second sweep over a larger grid runs only the new settings; the stored
    ones come back unchanged, a stage-1 setting matching its flat-schedule twin."""
    tuning = load_tuning()
    calls = []

    def runner(scenario, controller):
        calls.append(controller.tuning.q_position)
        return _fake_result(0.01 * abs(np.log10(controller.tuning.q_position / 100.0)) + 0.001)

    small = SweepGrid((("q_position", (30.0, 100.0)), ("q_yaw", (20.0,)), ("r_steer", (1.0,)),
                       ("p_steer_rate", (300.0,))))
    (first,) = run_sweep(["lmpc"], [_scenario("a")], tuning, weight_grid=small, runner=runner,
                         show_progress=False, low_speed_grid=NO_LOW_SPEED)
    stored = {("lmpc", e.setting): e for e in first.evaluations}
    calls.clear()
    (second,) = run_sweep(["lmpc"], [_scenario("a")], tuning, weight_grid=STAND_IN_WEIGHTS,
                          runner=runner, show_progress=False, low_speed_grid=NO_LOW_SPEED, reuse=stored)
    assert calls == [1000.0]  # 30 and 100 were stored
    assert [e.objective_m for e in second.evaluations[:2]] == [e.objective_m for e in first.evaluations]
    assert tuning_sweep.reuse_key((("q_position", 3.0), ("q_yaw", 20.0), ("r_steer", 1.0))) == \
        tuning_sweep.reuse_key((("q_position", 3.0), ("q_yaw", 20.0), ("r_steer", 1.0),
                                ("low_speed_q_position", 3.0), ("low_speed_q_yaw", 20.0),
                                ("low_speed_r_steer", 1.0)))


def test_geometric_controller_runs_its_own_grid_and_no_later_stage(tmp_path: Path) -> None:
    """Stanley (no MPC weights): stage 1 over its gain grid only, no observer or low-speed
    stage, its setting before the sweep reported; the report names its grid and rebuilds
    from the stored document."""
    import json

    tuning = load_tuning()
    gains = SweepGrid((("cross_track_gain", (1.0, 4.0, 16.0)), ("softening_speed", (1.0,)),
                       ("yaw_rate_gain", (0.0, 0.5)), ("steer_rate_limit", (1.0,)),
                       ("steer_time_constant", (0.0,))))

    def runner(scenario, controller):
        table = controller.tuning
        if not isinstance(table, StanleyTuning):
            return _fake_result(0.01)
        return _fake_result(0.01 * abs(np.log2(table.cross_track_gain / 4.0)) + 0.001 + 0.002 * table.yaw_rate_gain)

    sweeps = run_sweep(["lmpc", "stanley"], [_scenario("a")], tuning, weight_grid=STAND_IN_WEIGHTS,
                       runner=runner, show_progress=False, evaluate_before=True, gain_grids={StanleyTuning: gains})
    lmpc, stanley = sweeps
    assert lmpc.own_grid is None and stanley.own_grid is gains
    assert [e.stage for e in stanley.evaluations] == ["gains"] * len(gains)
    assert stanley.weight_fields == gains.fields and stanley.observer_fields == ()
    assert dict(stanley.chosen.setting) == {"cross_track_gain": 4.0, "softening_speed": 1.0, "yaw_rate_gain": 0.0,
                                            "steer_rate_limit": 1.0, "steer_time_constant": 0.0}
    assert stanley.before is not None and dict(stanley.before.setting) == {
        name: getattr(tuning.stanley, name) for name in STANLEY_GRID.fields}
    assert "low_speed_q_position" in lmpc.weight_fields  # the MPC still has stage 4
    markdown = tuning_sweep.sweep_markdown(sweeps, ["a"], {}, STAND_IN_WEIGHTS)
    assert "- Stage 1 of stanley (no MPC weights: its own gains, 6 settings; no stages 2-4)" in markdown
    assert "Stage 1: cross_track_gain {1, 4, 16}" in markdown.split("#### stanley")[1]
    document = json.loads(json.dumps(tuning_sweep.sweep_document(sweeps, ["a"], {}, STAND_IN_WEIGHTS)))
    record = tuning_sweep.sweep_from_document(document)
    assert record.sweeps[1].own_grid == gains and record.sweeps[1].weight_fields == gains.fields
    assert tuning_sweep.sweep_markdown(record.sweeps, ["a"], {}, STAND_IN_WEIGHTS) == markdown
    # The chosen gains go into the [stanley] table and load back.
    text = update_tuning_text(DEFAULT_TUNING_PATH.read_text(), {"stanley": stanley.chosen.setting})
    assert parse_tuning(tomllib.loads(text)).stanley.cross_track_gain == 4.0


def test_merge_carries_the_stored_controllers_over(tmp_path: Path) -> None:
    """--merge: the stored sweep's other controllers come back as stored, in its order, the
    controllers run now in their place or after; a carried controller on a model file that
    changed is refused."""
    import json

    path, stored = _stored_lmpc_dkmpc_sweep(tmp_path)
    artefact = {"Koopman artefact used": "dk_d5.npz sha256 aaaaaaaaaaaa"}
    carried = tuning_sweep.carried_sweeps(path, ["a"], ["stanley", "lmpc"], artefact)
    assert [s.controller for s in carried] == ["dkmpc"]
    assert [e.objective_m for e in carried[0].evaluations] == [e.objective_m for e in stored[1].evaluations]
    fresh = run_sweep(["stanley", "lmpc"], [_scenario("a")], load_tuning(), weight_grid=STAND_IN_WEIGHTS,
                      runner=lambda scenario, controller: _fake_result(0.02), show_progress=False,
                      low_speed_grid=NO_LOW_SPEED,
                      gain_grids={StanleyTuning: SweepGrid(tuple((name, values[:1]) for name, values in STANLEY_GRID.levels))})
    merged = tuning_sweep.merged_sweeps(tuning_sweep.sweep_from_document(json.loads(path.read_text())).sweeps, fresh)
    assert [s.controller for s in merged] == ["lmpc", "dkmpc", "stanley"]
    assert merged[0] is fresh[1] and merged[2] is fresh[0]
    with pytest.raises(StudyError, match="dkmpc"):
        tuning_sweep.carried_sweeps(path, ["a"], ["stanley"], {"Koopman artefact used": "dk_d5.npz sha256 b"})
    # Without dkmpc carried over, another artefact is no reason to refuse.
    assert tuning_sweep.carried_sweeps(path, ["a"], ["dkmpc"], {"Koopman artefact used": "other"})[0].controller == "lmpc"
    with pytest.raises(StudyError, match="scenarios"):
        tuning_sweep.carried_sweeps(path, ["b"], ["stanley"], artefact)


def test_cli_merge_needs_reuse(tmp_path: Path, capsys) -> None:
    status = tuning_sweep.main(["--controllers", "stanley", "--merge", "--out", str(tmp_path / "out"), "--no-write"])
    assert status == 1 and "--merge" in capsys.readouterr().err and not (tmp_path / "out").exists()

"""studies.paper_tables and studies.report: the study's files, tables and acceptance checks, run with the
test doubles (kinematic plant, pure pursuit) so it takes seconds."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

import studies.closed_loop as closed_loop
from studies.machine_figures import MACHINE_KEYS, split_machine_keys
from studies.report import PAPER_TRACKING, tracking_table
from hil.scenario import load_scenario
from studies.paper_tables import acceptance_checks, main, run_study, summary_text
from tests.test_closed_loop_doubles import KinematicCommand, KinematicPlant, PurePursuit


@pytest.fixture
def doubles(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every controller name builds a pure pursuit; the plant is the kinematic double."""
    import controller.registry as registry

    def create(name: str, tuning_path=None) -> PurePursuit:
        if name == "nmpc":
            raise FileNotFoundError("nmpc artefact missing (test)")
        controller = PurePursuit(lookahead_m=6.0 if name != "dkmpc" else 9.0)
        controller.name = name
        return controller

    monkeypatch.setattr(registry, "create_controller", create)
    monkeypatch.setattr(closed_loop, "default_plant",
                        lambda scenario: (KinematicPlant(), KinematicCommand))


def test_study_writes_tables_figures_json_and_traces(tmp_path: Path, doubles) -> None:
    scenarios = [replace(load_scenario("dlc_high_mu"), duration_s=3.0),
                 replace(load_scenario("dlc_low_mu"), duration_s=3.0)]
    document = run_study(scenarios, ["eso-dkmpc", "dkmpc", "lmpc", "nmpc"], tmp_path,
                         show_progress=False)
    for name in ("table2_high_mu.md", "table3_low_mu.md", "fig8_high_mu.png", "fig9_low_mu.png",
                 "study_checks.md", "study_metrics.json"):
        assert (tmp_path / name).stat().st_size > 200, name
    assert not (tmp_path / "compute_time.md").exists()  # compute time: make bench only
    assert len(list((tmp_path / "traces").glob("*.npz"))) == 6
    on_disk = json.loads((tmp_path / "study_metrics.json").read_text())
    inputs_only, timing = split_machine_keys(document["runs"])
    assert on_disk == json.loads(json.dumps({**document, "runs": inputs_only}))
    assert not any(set(run) & set(MACHINE_KEYS) for run in on_disk["runs"])  # the same on any host
    on_host = json.loads((tmp_path / "logs" / "tables_timing.json").read_text())
    assert on_host["runs"] == json.loads(json.dumps(timing)) and on_host["machine"]
    runs = {(r["scenario"], r["controller"]): r for r in on_disk["runs"]}
    assert runs[("dlc_low_mu", "nmpc")]["error"].startswith("FileNotFoundError")
    assert runs[("dlc_high_mu", "lmpc")]["completed"]
    assert runs[("dlc_high_mu", "lmpc")]["steps"] == 120
    table = (tmp_path / "table2_high_mu.md").read_text()
    print(table)
    assert "| ESO-DKMPC | yes |" in table and "0.217 / 0.066 / 0.093" in table
    assert "NMPC could not be built: FileNotFoundError" in table
    summary = summary_text(document)
    print(summary)
    assert "[FAIL] every controller completes" in summary and "nmpc on dlc_high_mu" in summary
    checks = (tmp_path / "study_checks.md").read_text()
    assert checks.startswith("- FAIL: every controller completes") and "nmpc on dlc_high_mu" in checks
    assert checks.count("\n- ") + 1 == len(on_disk["checks"])


def test_cli_reports_unbuildable_runs_and_bad_scenarios(tmp_path: Path, doubles, capsys) -> None:
    assert main(["--scenarios", "dlc_smoke", "--controllers", "nmpc", "--out", str(tmp_path),
                 "--no-progress"]) == 1
    assert "could not be built" in capsys.readouterr().err
    assert main(["--scenarios", "dlc_nowhere", "--out", str(tmp_path)]) == 1
    assert "error: unknown scenario 'dlc_nowhere'" in capsys.readouterr().err


def _run(scenario: str, controller: str, *, max_abs: float = 0.2, rmse: float = 0.1,
         median: float = 1e-3, completed: bool = True) -> dict:
    return {"scenario": scenario, "controller": controller, "completed": completed,
            "failure": None if completed else "stopped", "error": None,
            "tracking": {"lateral_error_m": {"max_abs": max_abs, "mean_abs": rmse, "rmse": rmse},
                         "heading_error_rad": {"max_abs": 0.01, "mean_abs": 0.01, "rmse": 0.01}},
            "compute_time": {"mean_s": median, "median_s": median, "p99_s": median,
                             "max_s": median, "steps": 10},
            "solver_time_mean_s": median / 2}


def _all_runs(changes: dict | None = None) -> list[dict]:
    changes = changes or {}
    runs = []
    for scenario in ("dlc_high_mu", "dlc_low_mu"):
        for controller, rmse in (("eso-dkmpc", 0.05), ("dkmpc", 0.08), ("lmpc", 0.1),
                                 ("nmpc", 0.09)):
            kwargs = {"rmse": rmse, "median": 2e-3}
            kwargs.update(changes.get((scenario, controller), {}))
            runs.append(_run(scenario, controller, **kwargs))
    return runs


def test_acceptance_checks_pass_and_fail_for_the_right_reasons() -> None:
    scenarios = ["dlc_high_mu", "dlc_low_mu"]
    controllers = ["eso-dkmpc", "dkmpc", "lmpc", "nmpc"]
    passed = acceptance_checks(_all_runs(), scenarios, controllers)
    assert [c["passed"] for c in passed] == [True, True, True]
    failing = acceptance_checks(_all_runs({
        ("dlc_low_mu", "lmpc"): {"max_abs": 2.3},
        ("dlc_high_mu", "eso-dkmpc"): {"rmse": 0.09, "median": 7e-3},
        ("dlc_low_mu", "eso-dkmpc"): {"median": 7e-3},
    }), scenarios, controllers)
    verdicts = {c["check"]: (c["passed"], c["detail"]) for c in failing}
    print(json.dumps(verdicts, indent=1))
    assert verdicts["every controller completes every scenario with |e_Y| < 2.0 m"] == \
        (False, "lmpc on dlc_low_mu: max |e_Y| = 2.300 m")
    assert verdicts["ESO-DKMPC e_Y RMSE < DKMPC's on dlc_high_mu"][0] is False
    assert verdicts["ESO-DKMPC e_Y RMSE < DKMPC's on dlc_low_mu"][0] is True
    assert not any("step time" in check for check in verdicts)  # a machine figure: make bench


def test_tables_carry_our_values_and_the_papers() -> None:
    runs = [_run("dlc_low_mu", "eso-dkmpc", max_abs=0.4567, rmse=0.1234),
            _run("dlc_low_mu", "lmpc", completed=False)]
    table = tracking_table("Table III", runs, "dlc_low_mu")
    assert "| ESO-DKMPC | yes | 0.457 / 0.123 / 0.123 |" in table
    paper_lmpc = " / ".join(f"{v:.3f}" for v in PAPER_TRACKING["dlc_low_mu"]["lmpc"][0])
    assert "| LMPC | no: stopped |" in table and paper_lmpc in table

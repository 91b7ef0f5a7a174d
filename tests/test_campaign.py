"""The campaign runner (studies/campaign): grid expansion and bad input, cache keys,
resume, failing and interrupted cells, a cell against ``python -m hil run``, the ecu axis
(the NMPC rule, keys of Python cells, the missing build, a real C ECU cell beside its
Python twin), and (slow) a 2-cell grid on a real Ray cluster started as separate
processes on 127.0.0.1."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from studies.campaign import runner
from studies.campaign.cell import CellJob, run_cell
from studies.campaign.grid import GridError, load_grid, to_toml
from studies.campaign.executors import SerialExecutor
from studies.campaign.report import summary_markdown, write_cells_csv, write_heatmaps
from studies.campaign.runner import CampaignError, cell_job, cell_key, run_campaign

ROOT = Path(__file__).resolve().parent.parent


def _grid(tmp_path: Path, text: str, name: str = "grid.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


GRID = """
name = "t"
[axes]
controller = ["lmpc", "dkmpc"]
scenario = ["dlc_smoke"]
mu = [0.5, 0.85]
lag_factor = [1.0, 3.0]
[[exclude]]
controller = "dkmpc"
mu = 0.5
[[exclude]]
lag_factor = 3.0
mu = [0.85]
"""


def test_grid_is_the_product_minus_the_exclusions(tmp_path):
    grid = load_grid(_grid(tmp_path, GRID))
    cells = {(c.controller, c.mu, c.lag_factor) for c in grid.cells}
    # 2 x 2 x 2 = 8; dkmpc at mu 0.5 (2) and lag 3 at mu 0.85 (2, one of them already out)
    assert cells == {("lmpc", 0.5, 1.0), ("lmpc", 0.5, 3.0), ("lmpc", 0.85, 1.0),
                     ("dkmpc", 0.85, 1.0)}
    assert grid.excluded == 4
    assert [c.controller for c in grid.cells] == ["lmpc"] * 3 + ["dkmpc"]


def test_model_axis_applies_to_the_koopman_controllers_only(tmp_path):
    grid = load_grid(_grid(tmp_path, """
[axes]
controller = ["lmpc", "dkmpc"]
scenario = ["dlc_smoke"]
model = ["default", "models/artifacts/dk_paper_nominal.npz"]
"""))
    assert [(c.controller, c.model) for c in grid.cells] == [
        ("lmpc", "default"), ("dkmpc", "default"), ("dkmpc", "models/artifacts/dk_paper_nominal.npz")]
    assert grid.not_applicable == 1


@pytest.mark.parametrize("body, words", [
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nfriction = [0.5]', ["friction", "unknown axis"]),
    ('[axes]\ncontroller = ["pid"]\nscenario = ["dlc_smoke"]', ["axes.controller", "'pid'"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["nowhere"]', ["axes.scenario", "'nowhere'"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nmu = [85]', ["axes.mu", "85"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nfault = ["gremlins"]', ["axes.fault", "gremlins"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\n[[exclude]]\nmu = 0.3', ["exclude[0].mu"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_high_mu"]\nspeed = [120.0]', ["path ends"]),
    ('[axes]\ncontroller = ["lmpc"]', ["axes.scenario is required"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\necu = ["rust"]', ["axes.ecu", "'rust'"]),
    ('[axes]\ncontroller = ["nmpc"]\nscenario = ["dlc_smoke"]\necu = ["c"]',
     ["no cell left", "the C ECU has no nmpc"]),
    # issue 38: the whole grid is valid before the first cell, or one error
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nlag_factor = [0.0]', ["axes.lag_factor", "[1.0, 100.0]"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nlag_factor = [0.5]', ["axes.lag_factor", "0.5", "[1.0, 100.0]"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nspeed = ["p"]\n'
     '[speed_profiles.p]\ntime_s = [0.0, nan]\ntarget_speed_kmh = [30.0, 40.0]', ["speed_profiles.p", "time_s"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nspeed = ["p"]\n'
     '[speed_profiles.p]\ntime_s = [0.0, 1.0]\ntarget_speed_kmh = [30.0, -40.0]', ["speed_profiles.p", "[0.0, 200.0] km/h"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nspeed = ["p"]\n'
     '[speed_profiles.p]\ntime_s = [0.0, 2.0, 1.0]\ntarget_speed_kmh = [30.0, 40.0, 40.0]',
     ["speed_profiles.p", "strictly increasing"]),
    ('[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\nspeed = ["p"]\n'
     '[speed_profiles.p]\ntime_s = [-1.0, 1.0]\ntarget_speed_kmh = [30.0, 40.0]', ["speed_profiles.p", "[0, 3600.0] s"]),
])
def test_bad_input_is_an_error_naming_the_key_and_the_file(tmp_path, body, words):
    file = _grid(tmp_path, body)
    with pytest.raises(GridError) as info:
        load_grid(file)
    message = str(info.value)
    print(message)
    assert str(file) in message
    for word in words:
        assert word in message


def test_a_grid_that_is_not_utf8_or_names_a_model_outside_the_repository_is_one_error(tmp_path):
    file = tmp_path / "latin.toml"
    file.write_bytes('name = "caf\u00e9"\n[axes]\ncontroller = ["lmpc"]\nscenario = ["dlc_smoke"]\n'.encode("latin-1"))
    with pytest.raises(GridError, match=f"{file}: not UTF-8 text"):
        load_grid(file)
    outside = Path(tempfile.mkdtemp(prefix="model-outside-"))   # not under the repository
    try:
        for suffix in (".npz", ".json"):
            shutil.copy(ROOT / "models" / "artifacts" / f"dk_paper_nominal{suffix}", outside / f"m{suffix}")
        grid = _grid(tmp_path, f'[axes]\ncontroller = ["dkmpc"]\nscenario = ["dlc_smoke"]\n'
                               f'model = ["{outside / "m.npz"}"]\n')
        with pytest.raises(GridError, match="is outside the repository"):
            load_grid(grid)
    finally:
        shutil.rmtree(outside)


def test_a_campaign_whose_cells_all_fail_to_run_exits_1(tmp_path, monkeypatch, capsys):
    from studies.campaign import __main__ as campaign_main
    from studies.campaign import cell

    def failing(job):
        return {"key": job.key, "e_y_rmse": float("nan"), "e_y_max": float("nan"),
                "heading_rmse": float("nan"), "completed": 0, "end_reason": "error",
                "step_p50_us": float("nan"), "step_p99_us": float("nan"), "overruns": 0,
                "error": "ScenarioError: broken"}

    monkeypatch.setattr(cell, "run_cell", failing)
    status = campaign_main.main([str(_grid(tmp_path, GRID)), "--out", str(tmp_path / "out"), "--serial",
                                 "--no-progress"])
    assert status == 1
    assert "error: every cell failed to run (the first: ScenarioError: broken)" in capsys.readouterr().err


def test_cache_keys_are_stable_and_tell_cells_and_code_apart(tmp_path):
    grid = load_grid(_grid(tmp_path, GRID))
    keys = [cell_key(grid, c, "code-1") for c in grid.cells]
    assert len(set(keys)) == len(keys)
    assert keys == [cell_key(grid, c, "code-1") for c in load_grid(_grid(tmp_path, GRID, "b.toml")).cells]
    assert cell_key(grid, grid.cells[0], "code-2") != keys[0]


ECU_GRID = """
name = "ecu"
[axes]
controller = ["lmpc", "nmpc"]
scenario = ["dlc_smoke"]
fault = ["none", "CAN FD look-alikes"]
ecu = ["python", "c"]
"""


def test_the_ecu_axis_leaves_out_what_the_c_ecu_cannot_run(tmp_path):
    """2 controllers x 2 faults x 2 ECUs = 8; the C ECU has no NMPC (2 cells) and its
    loopback hub cannot carry FD frames (LMPC's FD cell): 5 cells, 3 left out by reason,
    each C cell right after its Python twin."""
    grid = load_grid(_grid(tmp_path, ECU_GRID))
    assert [(c.controller, c.fault, c.ecu) for c in grid.cells] == [
        ("lmpc", "none", "python"), ("lmpc", "none", "c"), ("lmpc", "CAN FD look-alikes", "python"),
        ("nmpc", "none", "python"), ("nmpc", "CAN FD look-alikes", "python")]
    assert grid.excluded == 0 and grid.not_applicable == 0
    assert sorted(grid.c_left_out.values()) == [1, 2]
    assert grid.c_left_out["the C ECU has no nmpc (Python only)"] == 2
    assert any("FD" in reason and n == 1 for reason, n in grid.c_left_out.items())
    # an exclusion on the axis (before the rule: all 4 C cells excluded, none left out),
    # and a grid without the axis: the Python ECU only
    excluded = load_grid(_grid(tmp_path, ECU_GRID + '[[exclude]]\necu = "c"\n', "x.toml"))
    assert {c.ecu for c in excluded.cells} == {"python"}
    assert (excluded.excluded, dict(excluded.c_left_out)) == (4, {})
    plain = load_grid(_grid(tmp_path, GRID, "plain.toml"))
    assert {c.ecu for c in plain.cells} == {"python"} and not plain.c_left_out


def _stand_in_c_build(tmp_path: Path, monkeypatch) -> list[Path]:
    """Files in place of ``make firmware``'s build (the key hashes them; nothing runs)."""
    files = []
    for path in runner.C_ECU_FILES:
        stand_in = tmp_path / "c-build" / path.name
        stand_in.parent.mkdir(exist_ok=True)
        stand_in.write_bytes(path.name.encode())
        files.append(stand_in)
    monkeypatch.setattr(runner, "C_ECU_FILES", tuple(files))
    return files


def test_a_python_cells_key_does_not_depend_on_the_ecu_axis(tmp_path, monkeypatch):
    """A Python cell's key is the same with and without the axis (a cache from before the
    axis stays valid); a C cell's differs from its twin's and follows the C build's bytes."""
    files = _stand_in_c_build(tmp_path, monkeypatch)
    plain = load_grid(_grid(tmp_path, GRID))
    both = load_grid(_grid(tmp_path, GRID.replace('scenario = ["dlc_smoke"]',
                                                  'scenario = ["dlc_smoke"]\necu = ["python", "c"]'), "b.toml"))
    assert len(both.cells) == 2 * len(plain.cells)
    python = [cell_key(both, c, "code-1") for c in both.cells if c.ecu == "python"]
    c_keys = [cell_key(both, c, "code-1") for c in both.cells if c.ecu == "c"]
    assert python == [cell_key(plain, c, "code-1") for c in plain.cells]
    assert not set(c_keys) & set(python) and len(set(c_keys)) == len(c_keys)
    job = cell_job(both, both.cells[1], "code-1")
    assert (job.ecu, cell_job(both, both.cells[0], "code-1").ecu) == ("c", "python")
    files[0].write_bytes(b"another executable")
    assert cell_key(both, both.cells[1], "code-1") != c_keys[0]
    assert cell_key(both, both.cells[0], "code-1") == python[0]


def test_a_missing_c_build_is_one_error_before_any_cell(tmp_path, monkeypatch, capsys):
    from studies.campaign.__main__ import main

    missing = tmp_path / "no-build" / "ecu"
    monkeypatch.setattr(runner, "C_ECU_FILES", (missing, *runner.C_ECU_FILES[1:]))
    grid_file = _grid(tmp_path, ECU_GRID)
    ran: list[CellJob] = []
    with pytest.raises(CampaignError) as info:
        run_campaign(load_grid(grid_file), tmp_path / "out", SerialExecutor(ran.append), progress=False)
    assert str(missing) in str(info.value) and "make firmware" in str(info.value) and not ran
    assert main([str(grid_file), "--out", str(tmp_path / "cli"), "--serial", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    print(err)
    assert len(err) == 1 and err[0].startswith("error: ") and "`make firmware`" in err[0]
    assert 'axes.ecu has "c" (1 of the cells)' in err[0] and not (tmp_path / "cli").exists()


@pytest.fixture(scope="module")
def c_ecu_built() -> None:
    """``make firmware`` (a no-op when up to date); skipped only without a C compiler."""
    if shutil.which("gcc") is None:
        pytest.skip("no gcc: the C ECU cannot be built here (make firmware-deps installs it as root)")
    build = subprocess.run(["make", "-s", "--no-print-directory", "firmware"], cwd=ROOT,
                           capture_output=True, text=True, check=False)
    assert build.returncode == 0, build.stdout + build.stderr


def test_a_c_ecu_cell_runs_the_executable_beside_its_python_twin(tmp_path, c_ecu_built):
    """ESO-DKMPC on dlc_smoke on both ECUs, serially: the C cell completes with the
    executable's own step times, e_Y within 1 mm of the Python cell's RMSE (issue 18's
    lockstep equivalence), and the outputs carry the ecu column and the "(C)" columns."""
    grid = load_grid(_grid(tmp_path, """
name = "c-cell"
[axes]
controller = ["eso-dkmpc"]
scenario = ["dlc_smoke"]
ecu = ["python", "c"]
"""))
    result = run_campaign(grid, tmp_path / "out", SerialExecutor(run_cell), progress=False)
    python, c = result.rows
    print({k: c[k] for k in ("e_y_rmse", "e_y_max", "step_p50_us", "step_p99_us", "wall_s")},
          "python", {k: python[k] for k in ("e_y_rmse", "step_p99_us", "wall_s")})
    assert (python["ecu"], c["ecu"]) == ("python", "c")
    for row in (python, c):
        assert row["error"] == "" and row["completed"] == 1 and row["end_reason"] == "duration"
        assert 0.0 < row["e_y_rmse"] < 0.05 and row["e_y_max"] < 0.2
    assert abs(c["e_y_rmse"] - python["e_y_rmse"]) < 1e-3
    # the executable's CTRL_DIAG: its own step, well below the Python ECU's
    assert 0 < c["step_p50_us"] < python["step_p50_us"]
    write_cells_csv(tmp_path / "cells.csv", result.rows)
    with (tmp_path / "cells.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0])[:3] == ["controller", "ecu", "scenario"]
    assert [(r["controller"], r["ecu"]) for r in rows] == [("eso-dkmpc", "python"), ("eso-dkmpc", "c")]
    summary = summary_markdown(grid, result.rows, command="test", wall_s=result.wall_s,
                               executor="serial", computed=2, cached=0, machine="test")
    assert "| ESO-DKMPC | 1/1 |" in summary and "| ESO-DKMPC (C) | 1/1 |" in summary
    assert "## C ECU against the Python ECU" in summary
    assert "| ESO-DKMPC | 1 | 1 | 1 |" in summary  # one pair, same outcome, both completed
    assert write_heatmaps(grid, result.rows, tmp_path)[0].stat().st_size > 0


def _fake_row(job: CellJob) -> dict:
    return {"key": job.key, "e_y_rmse": 0.01, "e_y_max": 0.02, "heading_rmse": 0.003,
            "completed": 1, "end_reason": "duration", "error": ""}


def test_a_rerun_resumes_and_computes_only_what_is_missing(tmp_path):
    grid = load_grid(_grid(tmp_path, GRID))
    calls: list[str] = []

    def count(job):
        calls.append(job.key)
        return _fake_row(job)

    first = run_campaign(grid, tmp_path / "out", SerialExecutor(count), progress=False)
    assert (first.computed, first.cached, len(first.rows)) == (4, 0, 4)
    (tmp_path / "out" / "cache" / f"{calls[1]}.json").unlink()  # one result lost
    again = run_campaign(grid, tmp_path / "out", SerialExecutor(count), progress=False)
    assert (again.computed, again.cached) == (1, 3)
    assert calls[4] == calls[1]
    assert [r["key"] for r in again.rows] == [r["key"] for r in first.rows]


def test_cells_csv_tells_a_tuning_axis_settings_apart(tmp_path):
    grid = load_grid(_grid(tmp_path, """
name = "t"
[axes]
controller = ["lmpc"]
scenario = ["dlc_smoke"]
runner = "closed_loop"
tuning = ["file", "stiff"]
[tunings.stiff]
q_yaw = 200.0
"""))
    result = run_campaign(grid, tmp_path / "out", SerialExecutor(_fake_row), progress=False)
    with write_cells_csv(tmp_path / "cells.csv", result.rows).open() as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["controller"], r["runner"], r["tuning"]) for r in rows] == [
        ("lmpc", "closed_loop", "file"), ("lmpc", "closed_loop", "stiff")]


def test_a_failing_cell_is_recorded_and_the_campaign_goes_on(tmp_path):
    broken = run_cell(CellJob(key="k", controller="lmpc", scenario_toml='name = "x"\n'))
    assert broken["error"].startswith("ScenarioError") and broken["completed"] == 0
    assert broken["end_reason"] == "error"
    grid = load_grid(_grid(tmp_path, GRID))
    bad_key = cell_key(grid, grid.cells[1])

    def sometimes(job):
        return {**broken, "key": job.key} if job.key == bad_key else _fake_row(job)

    result = run_campaign(grid, tmp_path / "out", SerialExecutor(sometimes), progress=False)
    assert len(result.rows) == 4 and result.failed == 1
    assert result.rows[1]["error"].startswith("ScenarioError")


def test_ctrl_c_keeps_what_finished(tmp_path):
    grid = load_grid(_grid(tmp_path, GRID))
    seen: list[str] = []

    def interrupted_at_the_third(job):
        if len(seen) == 2:
            raise KeyboardInterrupt
        seen.append(job.key)
        return _fake_row(job)

    result = run_campaign(grid, tmp_path / "out", SerialExecutor(interrupted_at_the_third),
                          progress=False)
    assert result.interrupted and len(result.rows) == 2
    resumed = run_campaign(grid, tmp_path / "out", SerialExecutor(_fake_row), progress=False)
    assert (resumed.cached, resumed.computed) == (2, 2)


def test_scenario_toml_round_trips(tmp_path):
    grid = load_grid(_grid(tmp_path, """
[axes]
controller = ["lmpc"]
scenario = ["dlc_smoke"]
fault = ["drop 5 %"]
lag_factor = [3.0]
"""))
    import tomllib

    document = grid.scenario_document(grid.cells[0])
    assert tomllib.loads(to_toml(document)) == document
    assert document["faults"]["bus"][0]["kind"] == "drop"
    assert document["faults"]["vehicle"]["steer_extra_lag_s"] == pytest.approx(0.06)


def test_a_cell_is_the_run_hil_run_gives(tmp_path):
    """One cell (mu, mass, speed and steering lag changed) against ``python -m hil run
    --faults`` on the cell's scenario file: the same figures to the last bit."""
    grid = load_grid(_grid(tmp_path, """
[axes]
controller = ["lmpc"]
scenario = ["dlc_smoke"]
mu = [0.7]
speed = [40.0]
mass_offset_kg = [150.0]
lag_factor = [2.0]
"""))
    job = cell_job(grid, grid.cells[0], "test")
    row = run_cell(job)
    assert row["error"] == "" and row["completed"] == 1
    scenario = tmp_path / "cell.toml"
    scenario.write_text(job.scenario_toml.replace("{ROOT}", str(ROOT)), encoding="utf-8")
    out = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "hil", "run", "--scenario", str(scenario),
                    "--controller", "lmpc", "--faults", "--out", str(out)],
                   cwd=ROOT, check=True, capture_output=True, timeout=300)
    tracking = json.loads((out / "summary.json").read_text())["tracking"]
    direct = (tracking["lateral_error_m"]["rmse"], tracking["lateral_error_m"]["max_abs"],
              tracking["heading_error_rad"]["rmse"])
    cell = (row["e_y_rmse"], row["e_y_max"], row["heading_rmse"])
    print("cell", cell, "hil run", direct, "max abs difference",
          max(abs(a - b) for a, b in zip(cell, direct)))
    assert cell == direct


def _free_port() -> int:
    return _free_ports(1)[0]


def _free_ports(count: int) -> list[int]:
    """``count`` distinct ports free on 127.0.0.1 now (all bound at once, then released)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _ray_failure(log: Path, ray_dir: str, why: str) -> str:
    """``why`` with Ray's own words: the tail of ``ray start``'s output and of the newest
    files of its session's log folder."""
    parts = [why, "--- ray start output:", log.read_text(errors="replace")[-3000:]]
    logs = sorted(Path(ray_dir).glob("session_*/logs/*"), key=lambda f: f.stat().st_mtime)[-4:]
    for file in logs:
        if file.is_file():
            parts += [f"--- {file.name}:", file.read_text(errors="replace")[-1500:]]
    return "\n".join(parts)


def _stop_session(process: subprocess.Popen) -> None:
    """SIGTERM to ``process``'s session (``ray start --block`` then stops what it started),
    SIGKILL to what is left after 60 s."""
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=30)
    except ProcessLookupError:
        pass


@pytest.mark.slow
def test_a_grid_on_a_ray_cluster_started_as_processes(tmp_path):
    pytest.importorskip("ray", reason="Ray is not installed (make setup installs the campaign extra)")
    ray_cli = Path(sys.executable).with_name("ray")
    if not ray_cli.exists():
        ray_cli = Path(shutil.which("ray") or "ray")
    # Loopback only: the node registers as 127.0.0.1; token auth (Ray's default) on both sides.
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_AUTH_MODE": "token"}
    # A free port for every Ray component that listens (the dashboard agent's listen port
    # and the others are fixed by default, so another Ray or any service on them breaks
    # the start), and for the workers.
    (port, object_manager, node_manager, agent_listen, agent_grpc, runtime_env, metrics,
     *workers) = _free_ports(7 + 16)
    grid = _grid(tmp_path, """
name = "cluster"
[axes]
controller = ["lmpc", "dkmpc"]
scenario = ["dlc_smoke"]
""")
    # A short folder of its own: Ray's socket paths under it must stay within 107 bytes.
    ray_dir = tempfile.mkdtemp(prefix="ray-test-", dir="/tmp")
    # `ray start --block` in a session of its own, stopped by a signal to that session at
    # the end: `ray stop` would stop every Ray of this machine's user (a campaign running
    # beside the tests included), not only this test's cluster.
    ray_log = tmp_path / "ray_start.log"
    with ray_log.open("wb") as output:   # Ray's own words, for the failure message
        head = subprocess.Popen([str(ray_cli), "start", "--head", "--block", "--node-ip-address=127.0.0.1",
                                 f"--port={port}", f"--object-manager-port={object_manager}",
                                 f"--node-manager-port={node_manager}",
                                 f"--dashboard-agent-listen-port={agent_listen}",
                                 f"--dashboard-agent-grpc-port={agent_grpc}",
                                 f"--runtime-env-agent-port={runtime_env}", f"--metrics-export-port={metrics}",
                                 f"--worker-port-list={','.join(map(str, workers))}",
                                 "--num-cpus=2", "--include-dashboard=false",
                                 "--disable-usage-stats", f"--temp-dir={ray_dir}"],
                                env=env, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        # a loaded 2-core machine can take minutes to bring up the head's processes
        deadline = time.monotonic() + 300
        while subprocess.run([str(ray_cli), "status", f"--address=127.0.0.1:{port}"], env=env,
                             capture_output=True, timeout=120).returncode != 0:
            assert head.poll() is None, _ray_failure(ray_log, ray_dir,
                                                     f"ray start --head exited with status {head.returncode}")
            assert time.monotonic() < deadline, _ray_failure(ray_log, ray_dir,
                                                             "the Ray head did not come up within 300 s")
            time.sleep(1.0)
        run = subprocess.run([sys.executable, "-m", "studies.campaign", str(grid), "--out",
                              str(tmp_path / "out"), "--address", f"127.0.0.1:{port}",
                              "--no-progress"], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=600)
        print(run.stdout, run.stderr[-3000:])
        assert run.returncode == 0
        assert f"Ray cluster at 127.0.0.1:{port}" in (tmp_path / "out" / "summary.md").read_text()
        with (tmp_path / "out" / "cells.csv").open() as handle:
            rows = list(csv.DictReader(handle))
        assert [r["controller"] for r in rows] == ["lmpc", "dkmpc"]
        for row in rows:
            assert row["error"] == "" and row["completed"] == "1"
            assert 0.0 < float(row["e_y_rmse"]) < 0.1
    finally:
        _stop_session(head)
        shutil.rmtree(ray_dir, ignore_errors=True)

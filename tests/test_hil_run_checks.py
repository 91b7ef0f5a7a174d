"""``python -m hil run`` checks its inputs and outputs before anything runs (issue 17,
defects 5 and 6) and ends cleanly on SIGTERM / SIGHUP with the ECU as a separate process
(defect 7)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import pytest

from hil.bus import private_virtual_channel
from hil.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
DLC = REPO / "hil" / "paths" / "dlc.csv"


def quick_scenario(tmp_path: Path, duration_s: float = 0.3, path_file: Path = DLC) -> Path:
    source = load_scenario("dlc_smoke").source
    scenario = tmp_path / "quick.toml"
    scenario.write_text(source.read_text().replace("duration_s = 4.0", f"duration_s = {duration_s}")
                        .replace('"../paths/dlc.csv"', f'"{path_file}"'))
    return scenario


def hil_main(argv: list[str]) -> int:
    from hil.__main__ import main
    return main(argv)


def run_args(scenario: Path, *extra: str) -> list[str]:
    return ["run", "--scenario", str(scenario), "--controller", "lmpc", "--interface", "virtual",
            "--channel", private_virtual_channel("checks"), *extra]


def test_log_onto_the_runs_own_path_file_is_refused(tmp_path, capsys):
    """Issue 17, defect 5: ``hil run --log hil/paths/dlc.csv``: the recorder truncated the
    run's own input before the ECU read it; the reference path was destroyed."""
    path_copy = tmp_path / "dlc.csv"
    path_copy.write_bytes(DLC.read_bytes())
    scenario = quick_scenario(tmp_path, path_file=path_copy)
    status = hil_main(run_args(scenario, "--log", str(path_copy)))
    err = capsys.readouterr().err
    print(err)
    assert status == 2 and err.count("\n") == 1
    assert err.startswith(f"error: --log {path_copy}: is one of the inputs of this run")
    assert path_copy.read_bytes() == DLC.read_bytes()
    status = hil_main(run_args(scenario, "--log", str(scenario)))
    assert status == 2 and "is one of the inputs" in capsys.readouterr().err


def test_existing_out_file_is_refused_before_the_run(tmp_path, capsys):
    """Issue 17, defect 6: ``hil run --out FILE`` where FILE exists: FileExistsError traceback
    after the whole run, results lost. Now refused before the run starts."""
    scenario = quick_scenario(tmp_path)
    out = tmp_path / "results.txt"
    out.write_text("keep me")
    started = time.monotonic()
    status = hil_main(run_args(scenario, "--out", str(out)))
    err = capsys.readouterr().err
    print(err, f"after {time.monotonic() - started:.2f} s")
    assert status == 2 and err == f"error: --out {out}: is a file, expected a folder\n"
    assert out.read_text() == "keep me"


def test_outputs_of_another_run_need_replace_and_missing_folders_are_errors(tmp_path, capsys):
    scenario = quick_scenario(tmp_path)
    out, log = tmp_path / "out", tmp_path / "run.log"
    assert hil_main(run_args(scenario, "--out", str(out), "--log", str(log))) == 0
    capsys.readouterr()
    summary = (out / "summary.json").read_text()
    assert hil_main(run_args(scenario, "--out", str(out))) == 2
    err = capsys.readouterr().err
    assert "holds another run's outputs" in err and "--replace" in err
    assert hil_main(run_args(scenario, "--log", str(log))) == 2
    assert "file exists (give --replace" in capsys.readouterr().err
    assert (out / "summary.json").read_text() == summary
    assert hil_main(run_args(scenario, "--out", str(out), "--log", str(log), "--replace")) == 0
    capsys.readouterr()
    for option, target in (("--out", tmp_path / "no" / "out"), ("--log", tmp_path / "no" / "r.log")):
        assert hil_main(run_args(scenario, option, str(target))) == 2  # a bad option value
        err = capsys.readouterr().err
        print(err)
        assert err.startswith(f"error: {option} {target}: folder") and "does not exist" in err
    assert not (tmp_path / "no").exists()


def _processes_with(marker: str) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if marker in cmdline and "firmware_sim" in cmdline:
            found.append(int(entry.name))
    return found


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_end_a_run_with_a_separate_ecu_cleanly(tmp_path, signum):
    """Issue 17, defect 7: SIGTERM or SIGHUP to ``hil run`` with the ECU as a separate
    process orphaned the ECU, lost the log's buffered tail and the sidecar."""
    hub = subprocess.Popen([sys.executable, "-m", "hil.timing.hub"], cwd=REPO,
                           stdout=subprocess.PIPE, text=True)
    channel = f"sig{uuid.uuid4().hex[:8]}"
    try:
        port = int(hub.stdout.readline().split()[1])
        env = dict(os.environ, CAN_CONFIG=json.dumps({"host": "127.0.0.1", "port": port}),
                   OPENBLAS_NUM_THREADS="1")
        scenario = quick_scenario(tmp_path, duration_s=60.0)
        log = tmp_path / "run.log"
        run = subprocess.Popen([sys.executable, "-m", "hil", "run", "--scenario", str(scenario),
                                "--controller", "lmpc", "--interface", "socketcand",
                                "--channel", channel, "--log", str(log),
                                "--out", str(tmp_path / "out")],
                               cwd=REPO, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 20_000):
            time.sleep(0.2)   # the handshake is done and ticks run
        assert _processes_with(channel), "the ECU process did not start"
        run.send_signal(signum)
        status = run.wait(timeout=60)
        err = run.stderr.read()
        run.stdout.close()
        run.stderr.close()
    finally:
        hub.terminate()
        hub.wait(10)
        hub.stdout.close()
    left = _processes_with(channel)
    frames = list(can.LogReader(log))
    last_command = [m for m in frames if m.arbitration_id == 0x200][-1]
    sidecar = json.loads(Path(str(log) + ".json").read_text())
    print("last frames:", [(hex(m.arbitration_id), bytes(m.data).hex()) for m in frames[-4:]])
    print("ECU output:", (tmp_path / "out" / "ecu_output.txt").read_text()[-600:])
    print(f"exit {status}, stderr {err!r}, {len(frames)} frames logged, last command "
          f"{bytes(last_command.data).hex()}, ECU processes left {left}")
    assert status == 128 + signum
    assert err.strip().splitlines()[-1] == f"error: stopped by {signal.Signals(signum).name}"
    assert "Traceback" not in err
    assert left == []
    assert last_command.data[1] & 0x80 == 0  # CMD_VALID = 0 (bit 15)
    assert sidecar["controller"] == "lmpc"

"""``python -m hil replay``: reports, exit status and bad input, on the recorded logs."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import can
import pytest

from hil.logio import frame_times, read_log

LOGS = Path(__file__).parent / "data" / "logs"
LOCKSTEP = LOGS / "lockstep_lmpc.log"

pytest.importorskip("osqp")


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    """``python -m hil`` with the replay / decode / play subcommands registered."""
    import hil.__main__ as cli

    for name in ("replay", "decode", "play"):
        monkeypatch.setitem(cli.SUBCOMMANDS, name, f"hil.commands.{name}")
    return cli.main


def test_replay_against_the_reference_exits_0(hil_cli, capsys, tmp_path: Path) -> None:
    status = hil_cli(["replay", str(LOCKSTEP), "--ref", str(LOGS / "lockstep_lmpc.ref.log"),
                      "--json", str(tmp_path / "report.json")])
    out = capsys.readouterr().out
    print(out)
    assert status == 0
    assert "controller: lmpc (from the sidecar)" in out and "result: MATCH" in out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["match"] and report["frames"]["mismatched"] == 0


def test_diverging_replay_exits_3_and_names_the_first_divergence(hil_cli, capsys) -> None:
    status = hil_cli(["replay", str(LOGS / "faults_lmpc.asc")])
    out = capsys.readouterr().out
    print(out)
    assert status == 3
    # At the first fault (plant frames dropped from 0.50 s): the steer of the 0.500 s step or,
    # with a tuning whose steer rounds the same, the mode at 0.525 s (tests/test_replay_logs.py).
    assert re.search(r"first divergence: t = 0\.5(00|25) s, STEER_TORQUE_CMD\.(steer_angle_cmd|ctrl_mode)", out)
    assert "result: DIFFERENT" in out


def test_without_sidecar_the_controller_flag_is_required(hil_cli, capsys, tmp_path: Path) -> None:
    bare = tmp_path / "bare.log"
    shutil.copy(LOCKSTEP, bare)
    assert hil_cli(["replay", str(bare)]) == 1
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and "pass --controller NAME" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("args, message", [
    (["replay", "run.xyz", "--controller", "lmpc"], "unknown log format '.xyz'"),
    (["replay", "absent.log", "--controller", "lmpc"], "no such log file"),
    (["replay", str(LOCKSTEP), "--controller", "pid"], "unknown controller 'pid'"),
    (["replay", str(LOCKSTEP), "--tol", "steer=1"], "--tol 'steer=1'"),
    (["replay", str(LOCKSTEP), "--path", "1=/nonexistent.csv"], "cannot read /nonexistent.csv"),
])
def test_bad_input_is_one_error_line(hil_cli, capsys, args: list[str], message: str) -> None:
    assert hil_cli(args) == 1
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and message in err and "Traceback" not in err


def test_truncated_log_gives_a_warning_and_a_partial_report(hil_cli, capsys, tmp_path: Path) -> None:
    text = LOCKSTEP.read_text()
    cut = tmp_path / "cut.log"
    cut.write_text(text[: len(text) // 2 + 17])  # the recorder was killed mid-line
    shutil.copy(LOGS / "lockstep_lmpc.log.json", tmp_path / "cut.log.json")
    status = hil_cli(["replay", str(cut), "--ref", str(LOGS / "lockstep_lmpc.ref.log")])
    captured = capsys.readouterr()
    print(captured.err, captured.out)
    assert "warning:" in captured.err and "is incomplete (no line end)" in captured.err
    # Against the whole reference, the frames after the cut are missing: reported, not hidden.
    assert status == 3 and "missing" in captured.out
    status = hil_cli(["replay", str(cut)])
    captured = capsys.readouterr()
    print(captured.out)
    assert status == 0 and "result: MATCH" in captured.out


def test_write_ref_then_compare_with_it(hil_cli, capsys, tmp_path: Path) -> None:
    reference = tmp_path / "lockstep.ref.log"
    assert hil_cli(["replay", str(LOCKSTEP), "--write-ref", str(reference)]) == 0
    assert "wrote" in capsys.readouterr().err  # stdout: the report only
    assert reference.read_text() == (LOGS / "lockstep_lmpc.ref.log").read_text()


def test_log_from_elsewhere_replays_with_a_clear_report(hil_cli, capsys, tmp_path: Path) -> None:
    """A log of the same DBC from another tool: no HIL frames, timestamps only, foreign IDs
    on the bus. The replay runs the ECU on the log's clock and compares per signal."""
    contents = read_log(LOCKSTEP)
    times, _ = frame_times(contents.messages)
    other = tmp_path / "vector.asc"
    with can.Logger(other) as writer:
        for message, time_s in zip(contents.messages, times):
            if message.arbitration_id in (0x080, 0x081):
                continue
            writer.on_message_received(can.Message(timestamp=7.0 + time_s, data=message.data,
                                                   arbitration_id=message.arbitration_id,
                                                   is_extended_id=False))
            if message.arbitration_id == 0x110:  # a gateway's frame every 25 ms
                writer.on_message_received(can.Message(timestamp=7.0 + time_s, data=b"\x00\x01",
                                                       arbitration_id=0x3E8, is_extended_id=False))
    status = hil_cli(["replay", str(other), "--controller", "lmpc"])
    out = capsys.readouterr().out
    print(out)
    assert status == 0 and "result: MATCH" in out
    assert "no HIL_SYNC in the log" in out and "per signal with tolerances" in out
    assert "80 frame(s) with IDs outside the contract's DBC" in out
    assert "paths: 1=" in out and "default: hil/paths/dlc.csv" in out


def test_a_real_time_recording_is_refused_unless_a_comparison_that_can_hold_is_asked_for(
        hil_cli, capsys, tmp_path: Path) -> None:
    """A ``--realtime`` run's commands depend on the host's timing, which no log holds: a
    plain replay says so up front (exit 1, one line) instead of a DIFFERENT for timing
    alone; ``--compare tolerance`` and a replay's own reference run as asked."""
    realtime = LOGS / "realtime_lmpc.blf"
    for extra in ([], ["--compare", "exact"], ["--json"]):
        status = hil_cli(["replay", str(realtime), *extra])
        captured = capsys.readouterr()
        assert status == 1 and captured.out == "" and captured.err.count("\n") == 1, captured
        assert captured.err.startswith(f"error: {realtime}: a real-time recording")
        assert "host's timing" in captured.err and "--compare tolerance" in captured.err
    status = hil_cli(["replay", str(realtime), "--compare", "tolerance"])
    out = capsys.readouterr().out
    assert status in (0, 3) and "comparison: per signal with tolerances" in out
    status = hil_cli(["replay", str(realtime), "--ref", str(LOGS / "realtime_lmpc.ref.log")])
    assert status == 0 and "result: MATCH" in capsys.readouterr().out
    assert hil_cli(["replay", str(realtime), "--write-ref", str(tmp_path / "rt.ref.log")]) == 0
    # the same frames without the sidecar (a log of another tool): compared as before
    bare = tmp_path / "bare.blf"
    shutil.copy(realtime, bare)
    capsys.readouterr()
    assert hil_cli(["replay", str(bare), "--controller", "lmpc"]) in (0, 3)
    assert "comparison: per signal with tolerances" in capsys.readouterr().out

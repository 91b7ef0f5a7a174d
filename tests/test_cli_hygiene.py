"""Command lines as CAN engineers expect (issue 19): console commands, quiet on a closed
pipe, JSON alone on stdout, warnings once, choices checked up front, python-can's
configuration chain kept whole, a socketcan hint that tells the two failures apart,
output paths checked before anything runs, progress bars only on a terminal."""
from __future__ import annotations

import dataclasses
import errno
import io
import json
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import can
import pytest

from hil.bus import BusConfig, private_virtual_channel, resolve_bus_config, socketcan_hint

ROOT = Path(__file__).resolve().parent.parent
LOGS = Path(__file__).parent / "data" / "logs"
LOCKSTEP = LOGS / "lockstep_lmpc.log"
BIN = Path(sys.executable).parent


@pytest.fixture
def hil_cli():
    import hil.__main__ as cli

    return cli.main


@pytest.mark.parametrize("name, target", [("eso-ecu", "firmware_sim.cli:entry"),
                                          ("eso-hil", "hil.__main__:entry")])
def test_console_commands_resolve(name: str, target: str) -> None:
    points = {p.name: p for p in metadata.entry_points(group="console_scripts")}
    assert name in points, f"{name} not installed: run make setup"
    assert points[name].value == target and callable(points[name].load())
    script = BIN / name
    assert script.is_file(), f"{script} missing: make setup installs it"
    done = subprocess.run([str(script), "--help"], capture_output=True, text=True, timeout=60)
    print(done.stdout[:200])
    assert done.returncode == 0 and "usage:" in done.stdout


def test_a_closed_pipe_ends_quietly() -> None:
    """``eso-hil decode LOG | head -1``: the reader is gone before the output is flushed."""
    process = subprocess.Popen([str(BIN / "eso-hil"), "decode", str(LOCKSTEP)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # as head does after its line
    _, err = process.communicate(timeout=60)
    print(process.returncode, err.decode())
    assert process.returncode == 141 and b"Traceback" not in err and b"BrokenPipe" not in err


def test_run_json_alone_on_stdout_and_controller_in_any_case(hil_cli, capsys, tmp_path) -> None:
    from hil.scenario import load_scenario

    source = load_scenario("dlc_smoke").source
    scenario = tmp_path / "quick.toml"
    scenario.write_text(source.read_text().replace("duration_s = 4.0", "duration_s = 0.2")
                        .replace('"../paths/dlc.csv"', f'"{source.parent.parent / "paths/dlc.csv"}"'))
    status = hil_cli(["run", "--scenario", str(scenario), "--controller", "LMPC",
                      "--interface", "virtual", "--channel", private_virtual_channel("json"),
                      "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    print(captured.err)
    assert status == 0
    summary = json.loads(captured.out)  # nothing else on stdout
    assert summary["controller"] == "lmpc" and summary["control_cycles"] == 8
    assert captured.err.count("wrote ") == 3


@pytest.mark.parametrize("name", ["mpc", "pid", ""])
def test_an_unknown_controller_stops_before_anything_starts(hil_cli, capsys, name) -> None:
    status = hil_cli(["run", "--scenario", "dlc_smoke", "--controller", name])
    captured = capsys.readouterr()
    print(captured.err)
    assert status == 2 and captured.out == ""  # a bad option value, as eso-ecu's
    assert captured.err.count("\n") == 1 and captured.err.count("unknown controller") == 1


def test_the_ecu_takes_controller_names_in_any_case() -> None:
    from firmware_sim.cli import build_parser

    args = build_parser().parse_args(["--controller", "ESO-DKMPC", "--path",
                                      f"1={ROOT / 'hil/paths/dlc.csv'}", "--lockstep"])
    assert args.controller == "eso-dkmpc"


def test_a_channel_only_canrc_is_honoured(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(can, "rc", {})
    if Path("/etc/can.conf").exists():
        pytest.skip("/etc/can.conf configures python-can on this machine")
    (tmp_path / ".canrc").write_text("[default]\nchannel = vcan7\n")
    assert resolve_bus_config() == BusConfig("virtual", "vcan7")
    assert resolve_bus_config(channel="vcan3") == BusConfig("virtual", "vcan3")
    (tmp_path / ".canrc").write_text("[default]\ninterface = socketcan\n")
    assert resolve_bus_config() == BusConfig("socketcan", "vcan0")
    (tmp_path / ".canrc").write_text("[default]\ninterface = nosuchcan\nchannel = x\n")
    from hil.bus import BusOpenError

    with pytest.raises(BusOpenError, match="nosuchcan"):
        resolve_bus_config()


def test_the_socketcan_hint_tells_no_can_from_no_device() -> None:
    config = BusConfig("socketcan", "vcan9")
    no_can = socketcan_hint(config, OSError(errno.EAFNOSUPPORT, "Address family not supported"))
    no_device = socketcan_hint(config, OSError(errno.ENODEV, "No such device"))
    print(no_can, no_device, sep="\n")
    assert "kernel has no SocketCAN" in no_can and "ip link add" not in no_can
    assert "no device vcan9" in no_device and "ip link add dev vcan9 type vcan" in no_device
    assert socketcan_hint(BusConfig("virtual", "x"), None) == ""


def test_a_warning_is_printed_once(hil_cli, capsys, tmp_path) -> None:
    cut = tmp_path / "cut.log"
    text = LOCKSTEP.read_text()
    cut.write_text(text[: len(text) // 3 + 11])
    assert hil_cli(["decode", str(cut)]) == 0
    captured = capsys.readouterr()
    print(captured.err, captured.out)
    both = captured.out + captured.err
    assert both.count("is incomplete (no line end)") == 1


@pytest.mark.parametrize("option", ["--csv", "--plot"])
def test_decode_checks_its_outputs_up_front(hil_cli, capsys, tmp_path, option) -> None:
    existing = tmp_path / "exists.out"
    existing.write_text("keep")
    assert hil_cli(["decode", str(LOCKSTEP), option, str(existing)]) == 1
    assert "file exists (give --replace" in capsys.readouterr().err
    assert existing.read_text() == "keep"
    assert hil_cli(["decode", str(LOCKSTEP), option, str(tmp_path / "no" / "x.out")]) == 1
    err = capsys.readouterr()
    assert "does not exist" in err.err and err.out == ""  # nothing read, nothing printed


def test_replay_checks_its_outputs_up_front(hil_cli, capsys, tmp_path) -> None:
    existing = tmp_path / "report.json"
    existing.write_text("{}")
    for args in (["--json", str(existing)], ["--write-ref", str(existing)],
                 ["--json", str(tmp_path / "missing" / "r.json")]):
        assert hil_cli(["replay", str(LOCKSTEP), *args]) == 1
        captured = capsys.readouterr()
        assert captured.err.startswith("error: --") and captured.out == "", captured
    assert existing.read_text() == "{}"


def test_replay_json_alone_on_stdout_and_exit_codes(hil_cli, capsys) -> None:
    status = hil_cli(["replay", str(LOCKSTEP), "--json"])
    captured = capsys.readouterr()
    assert status == 0 and json.loads(captured.out)["match"] is True
    assert "result: MATCH" in captured.err
    # DIFFERENT is 3 in the tolerance comparison too (the faulty log's first fault).
    status = hil_cli(["replay", str(LOGS / "faults_lmpc.asc"), "--compare", "tolerance", "--json"])
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    print(report["first_divergence"])
    assert status == 3 and report["match"] is False and report["mode"] == "tolerance"


def test_progress_bars_only_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.commands import PROGRESS_MIN_FRAMES, progress

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    items = list(range(PROGRESS_MIN_FRAMES))
    for stream, quiet, shown in ((io.StringIO(), False, False), (Terminal(), True, False),
                                 (Terminal(), False, True)):
        monkeypatch.setattr(sys, "stderr", stream)
        assert list(progress(items, len(items), "replay", quiet)) == items
        assert ("replay:" in stream.getvalue()) == shown, stream.getvalue()
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    short = list(range(10))
    assert list(progress(short, len(short), "replay", False)) == short
    assert terminal.getvalue() == ""  # short logs: no bar


def test_decode_json_alone_on_stdout(hil_cli, capsys, tmp_path) -> None:
    status = hil_cli(["decode", str(LOGS / "faults_lmpc.asc"), "--json",
                      "--csv", str(tmp_path / "d.csv")])
    captured = capsys.readouterr()
    summary = json.loads(captured.out)  # nothing else on stdout
    print(captured.err)
    assert status == 0 and "wrote" in captured.err
    assert summary["e2e_verdicts"]["crc_error"] == 1 and summary["frames_per_message"]["VEH_DYN"] == 195
    assert summary["frames"] == 1628 and summary["wrote"] == [str(tmp_path / "d.csv")]

"""MF4 (ASAM MDF 4) logs (issue 39): a lockstep run recorded to ``.mf4`` decodes through
the DBC (``eso-hil decode``, and asammdf itself from the DBC attached to the file) and
replays to a MATCH; a cut MF4 is one error line; ``.mf4.gz`` is refused."""
from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import can
import pytest

from can_defs.dbc import DBC_PATH
from can_defs.frames import FrameId
from can_defs.log_reader import LogFormatError, LogReadError, check_log_suffix, read_log_frames
from hil.logio import read_log, read_sidecar
from hil.recorder import transmitted_ids

pytest.importorskip("asammdf")
pytest.importorskip("osqp")

CONTROLLER = "lmpc"
DURATION_S = 1.0


@pytest.fixture(scope="module")
def mf4_log(tmp_path_factory) -> Path:
    """A 1 s lockstep run of dlc_smoke recorded to MF4 (the rig's recorder, as ``eso-hil
    run --log run.mf4`` does)."""
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    scenario = dataclasses.replace(load_scenario("dlc_smoke"), duration_s=DURATION_S)
    log = tmp_path_factory.mktemp("mf4") / "run.mf4"
    run_hil(scenario, default_options(CONTROLLER, log_path=log))
    return log


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    import hil.__main__ as cli

    monkeypatch.setitem(cli.SUBCOMMANDS, "decode", "hil.commands.decode")
    return cli.main


def test_the_mf4_log_holds_the_run_with_directions(mf4_log: Path) -> None:
    frames = list(can.LogReader(mf4_log))  # python-can's own reader
    contents = read_log(mf4_log)
    print("\n".join(contents.summary_lines()))
    assert contents.complete and not contents.warnings and contents.is_lockstep
    assert len(contents.messages) == len(frames) > 300
    assert contents.frames_by_id[FrameId.STEER_TORQUE_CMD] >= DURATION_S / 0.025
    tx = transmitted_ids()
    assert all(m.is_rx == (m.arbitration_id not in tx) for m in frames)
    assert read_sidecar(mf4_log).controller == CONTROLLER


def test_the_mf4_log_replays_as_match(mf4_log: Path) -> None:
    from hil.replay import run_replay

    metadata = read_sidecar(mf4_log)
    report = run_replay(read_log(mf4_log), metadata.controller, dict(metadata.paths))
    print(report.text())
    assert report.comparison.mode == "exact"
    assert report.match and report.comparison.paired == report.comparison.expected > 40


def test_decode_writes_the_signals_of_an_mf4_log(mf4_log: Path, hil_cli, capsys,
                                                 tmp_path: Path) -> None:
    out = tmp_path / "decoded.csv"
    assert hil_cli(["decode", str(mf4_log), "--csv", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    print(summary)
    assert summary["complete"] and summary["e2e_verdicts"].get("ok", 0) > 300
    assert set(summary["e2e_verdicts"]) == {"ok"}
    with out.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    commands = [r for r in rows if r["frame"] == "STEER_TORQUE_CMD"]
    assert len(rows) == summary["frames"] and commands
    assert all(r["steer_angle_cmd"] != "" for r in commands)
    # with another DBC (a copy of the contract's): the signals through cantools, in
    # MESSAGE.SIGNAL columns
    other = tmp_path / "other.dbc"
    other.write_bytes(DBC_PATH.read_bytes())
    assert hil_cli(["decode", str(mf4_log), "--dbc", str(other), "--csv",
                    str(tmp_path / "dbc.csv")]) == 0
    with (tmp_path / "dbc.csv").open(newline="") as handle:
        by_dbc = list(csv.DictReader(handle))
    assert len(by_dbc) == len(rows)
    assert [r["STEER_TORQUE_CMD.STEER_ANGLE_CMD"] for r in by_dbc if r["frame"] == "STEER_TORQUE_CMD"]


def test_asammdf_decodes_the_log_with_the_attached_dbc(mf4_log: Path, tmp_path: Path) -> None:
    from asammdf import MDF

    with MDF(mf4_log) as mdf:
        attached = {attachment.file_name: attachment for attachment in mdf.attachments}
        assert str(next(iter(attached))).endswith("vehicle.dbc")
        dbc = tmp_path / "attached.dbc"
        dbc.write_bytes(mdf.extract_attachment(0)[0])
        assert dbc.read_bytes() == DBC_PATH.read_bytes()
        decoded = mdf.extract_bus_logging({"CAN": [(str(dbc), 0)]})
    steer = decoded.get("STEER_ANGLE_CMD")
    count = read_log(mf4_log).frames_by_id[FrameId.STEER_TORQUE_CMD]
    print(f"asammdf: {len(steer.samples)} STEER_ANGLE_CMD samples, {count} frames in the log")
    assert len(steer.samples) == count
    assert max(abs(float(v)) for v in steer.samples) <= 0.3


def test_a_cut_mf4_is_one_error(mf4_log: Path, tmp_path: Path, capfd) -> None:
    raw = mf4_log.read_bytes()
    for size in (100, len(raw) // 2, 3 * len(raw) // 4):
        cut = tmp_path / "cut.mf4"
        cut.write_bytes(raw[:size])
        with pytest.raises(LogReadError, match=r"cut\.mf4: not a readable \.mf4 log \(cut"):
            read_log_frames(cut)
    (tmp_path / "text.mf4").write_text("not a measurement\n")
    with pytest.raises(LogReadError, match=r"text\.mf4: not a readable \.mf4 log"):
        read_log_frames(tmp_path / "text.mf4")
    err = capfd.readouterr().err
    print(err)
    assert "Exception ignored" not in err and "Traceback" not in err


def test_mf4_has_no_gzip_form() -> None:
    assert check_log_suffix("run.mf4") == ".mf4"
    with pytest.raises(LogFormatError, match=r"run\.mf4\.gz: a \.mf4 log is compressed inside"):
        check_log_suffix("run.mf4.gz")

"""Logs of another bus, written by python-can's own writers as third-party tools write
them (ASC, BLF, TRC; CAN FD, error, remote and extended frames), decoded, played and
refused by the HIL commands (issue 19): ``--dbc`` decodes a foreign log with its DBC, the
project's DBC gives a warning instead of an empty figure, ``replay`` refuses a log
without the ECU's inputs (also with ``--write-ref``)."""
from __future__ import annotations

import csv
import threading
from pathlib import Path

import can
import pytest

from hil.bus import private_virtual_channel

FOREIGN_DBC = """VERSION ""

NS_ :

BS_:

BU_: ENGINE_ECU GATEWAY

BO_ 291 ENGINE: 8 ENGINE_ECU
 SG_ RPM : 0|16@1+ (0.25,0) [0|16383.75] "rpm" GATEWAY
 SG_ COOLANT : 16|8@1+ (1,-40) [-40|215] "degC" GATEWAY

BO_ 2566844672 WHEEL_SPEED: 8 GATEWAY
 SG_ FRONT_LEFT : 0|16@1+ (0.01,0) [0|655.35] "km/h" ENGINE_ECU
"""
ENGINE_ID = 0x123
WHEEL_ID = 0x18FEF100  # extended: 2566844672 = 0x80000000 | 0x18FEF100 in the DBC
N_ENGINE = 60


def _frames() -> list[can.Message]:
    """60 ENGINE frames every 10 ms, a wheel speed (extended ID) every 20 ms, a CAN FD
    frame, an error frame and a remote frame."""
    frames = []
    for i in range(N_ENGINE):
        t = 100.0 + i * 0.01
        rpm_raw = int((800 + 20 * i) / 0.25)
        frames.append(can.Message(timestamp=t, arbitration_id=ENGINE_ID, is_extended_id=False,
                                  data=rpm_raw.to_bytes(2, "little") + bytes([90 + 40]) + bytes(5)))
        if i % 2 == 0:
            frames.append(can.Message(timestamp=t + 0.001, arbitration_id=WHEEL_ID,
                                      data=int(5000 + 10 * i).to_bytes(2, "little") + bytes(6)))
    frames.append(can.Message(timestamp=100.2, arbitration_id=0x2A0, is_extended_id=False,
                              is_fd=True, bitrate_switch=True, data=bytes(range(12))))
    frames.append(can.Message(timestamp=100.3, is_error_frame=True))
    frames.append(can.Message(timestamp=100.4, arbitration_id=ENGINE_ID, is_extended_id=False,
                              is_remote_frame=True, dlc=8))
    return sorted(frames, key=lambda m: m.timestamp)


@pytest.fixture(scope="module")
def dbc(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("dbc") / "engine.dbc"
    path.write_text(FOREIGN_DBC)
    return path


@pytest.fixture(scope="module", params=[".asc", ".blf", ".trc"])
def foreign_log(request, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("foreign") / f"engine{request.param}"
    with can.Logger(path) as writer:  # python-can's ASCWriter / BLFWriter / TRCWriter
        for message in _frames():
            writer.on_message_received(message)
    return path


def special_frames(log: Path) -> int:
    """1 when the writer kept the FD, error and remote frame; python-can's TRCWriter
    leaves them out (with a logged warning), as PCAN's TRC 2.1 has no place for them."""
    return 0 if log.suffix == ".trc" else 1


@pytest.fixture
def hil_cli():
    import hil.__main__ as cli

    return cli.main


def test_a_foreign_log_decodes_with_its_dbc(hil_cli, capsys, foreign_log, dbc, tmp_path) -> None:
    out_csv, out_png = tmp_path / "engine.csv", tmp_path / "engine.png"
    status = hil_cli(["decode", str(foreign_log), "--dbc", str(dbc), "--csv", str(out_csv),
                      "--plot", str(out_png)])
    captured = capsys.readouterr()
    print(captured.out, captured.err)
    assert status == 0
    # ENGINE: its data frames and its remote frame
    remote = special_frames(foreign_log)
    assert (f"frames of engine.dbc: {N_ENGINE + remote + N_ENGINE // 2} "
            f"(ENGINE {N_ENGINE + remote}") in captured.out
    assert "E2E verdicts" not in captured.out  # no contract E2E in a foreign DBC
    with out_csv.open() as handle:
        rows = list(csv.DictReader(handle))
    engine = [r for r in rows if r["frame"] == "ENGINE"]
    wheel = [r for r in rows if r["frame"] == "WHEEL_SPEED"]
    assert len(engine) == N_ENGINE and len(wheel) == N_ENGINE // 2
    assert [float(r["ENGINE.RPM"]) for r in engine[:3]] == [800.0, 820.0, 840.0]
    assert float(engine[0]["ENGINE.COOLANT"]) == 90.0
    assert float(wheel[1]["WHEEL_SPEED.FRONT_LEFT"]) == pytest.approx(50.2)
    if special_frames(foreign_log):
        assert {"(error frame)", "ENGINE (remote)", "(not in DBC)"} <= {r["frame"] for r in rows}
    assert out_png.read_bytes()[:4] == b"\x89PNG" and out_png.stat().st_size > 20_000


def test_the_project_dbc_warns_instead_of_an_empty_figure(hil_cli, capsys, foreign_log,
                                                          tmp_path) -> None:
    out_png = tmp_path / "empty.png"
    status = hil_cli(["decode", str(foreign_log), "--plot", str(out_png)])
    captured = capsys.readouterr()
    print(captured.out, captured.err)
    assert status == 0 and not out_png.exists()
    assert captured.err.count("nothing to plot") == 1 and "--dbc FILE" in captured.err
    assert "contract frames: 0" in captured.out
    # the classic data frames of other IDs; the FD frame is no contract frame (not judged)
    assert f"E2E verdicts: unknown_id {N_ENGINE}" in captured.out
    if special_frames(foreign_log):
        assert "CAN FD frames: 1" in captured.out, captured.out


def test_replay_refuses_a_log_without_the_ecus_inputs(hil_cli, capsys, foreign_log,
                                                      tmp_path) -> None:
    for extra in ([], ["--write-ref", str(tmp_path / "ref.log")]):
        status = hil_cli(["replay", str(foreign_log), "--controller", "lmpc", *extra])
        captured = capsys.readouterr()
        print(captured.err)
        assert status == 1 and "Traceback" not in captured.err
        assert captured.err.startswith("error: ") and "none of the ECU's input frames" in captured.err
        assert "MATCH" not in captured.out and "DIFFERENT" not in captured.out
    assert not (tmp_path / "ref.log").exists()


def test_play_sends_the_messages_named_in_the_dbc(hil_cli, capsys, foreign_log, dbc) -> None:
    channel = private_virtual_channel("foreign-play")
    listener = can.Bus(interface="virtual", channel=channel)
    received: list[can.Message] = []
    done = threading.Event()

    def listen() -> None:
        while not done.is_set():
            message = listener.recv(timeout=0.05)
            if message is not None:
                received.append(message)

    thread = threading.Thread(target=listen)
    thread.start()
    try:
        status = hil_cli(["play", str(foreign_log), "--dbc", str(dbc), "--ids", "engine",
                          "--interface", "virtual", "--channel", channel, "--speed", "20"])
    finally:
        done.set()
        thread.join()
        # frames still queued when the thread saw `done`
        while (message := listener.recv(timeout=0.05)) is not None:
            received.append(message)
        listener.shutdown()
    captured = capsys.readouterr()
    print(captured.out)
    assert status == 0
    # The ENGINE data frames and its remote frame; error frames are left out (can.player).
    assert {m.arbitration_id for m in received} == {ENGINE_ID}
    remote = special_frames(foreign_log)
    assert len(received) == N_ENGINE + remote and sum(m.is_remote_frame for m in received) == remote


def test_play_leaves_error_frames_out_unless_asked(hil_cli, capsys, foreign_log) -> None:
    channel = private_virtual_channel("foreign-err")
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        for flags, expected in (([], 0), (["--error-frames"], special_frames(foreign_log))):
            assert hil_cli(["play", str(foreign_log), "--ignore-timestamps", "--interface",
                            "virtual", "--channel", channel, *flags]) == 0
            got = []
            while (message := listener.recv(timeout=0.05)) is not None:
                got.append(message)
            print(capsys.readouterr().out)
            assert sum(m.is_error_frame for m in got) == expected
    finally:
        listener.shutdown()

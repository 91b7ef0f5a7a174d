"""hil.player and ``python -m hil play``: timing, ID filter, E2E rewriting."""
from __future__ import annotations

import os
import time
from pathlib import Path

import can
import pytest

from can_defs.e2e import E2EMonitor, E2EStatus
from can_defs.frames import FrameId
from hil.logio import read_log
from hil.player import PlayError, parse_ids, play, rewrite_e2e, scale_timing, select_ids

LOGS = Path(__file__).parent / "data" / "logs"


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    """``python -m hil`` with the play subcommand registered."""
    import hil.__main__ as cli

    monkeypatch.setitem(cli.SUBCOMMANDS, "play", "hil.commands.play")
    return cli.main


def _verdicts(messages: list[can.Message]) -> dict[str, int]:
    monitor = E2EMonitor()
    for message in messages:
        monitor.check(message.arbitration_id, bytes(message.data))
    return {status.value: n for status, n in monitor.stats.counts.items() if n}


def test_rewrite_leaves_a_good_log_unchanged() -> None:
    messages = read_log(LOGS / "lockstep_lmpc.log").messages
    rewritten, stats = rewrite_e2e(messages)
    print(stats)
    assert [bytes(m.data) for m in rewritten] == [bytes(m.data) for m in messages]
    assert stats.counters_changed == 0 and stats.crcs_fixed == 0
    assert stats.renumbered[FrameId.VEH_DYN] == 200


def test_rewrite_makes_an_edited_log_well_formed() -> None:
    messages = read_log(LOGS / "faults_lmpc.asc").messages
    before = _verdicts(messages)
    rewritten, stats = rewrite_e2e(messages)
    after = _verdicts(rewritten)
    print(before, after, stats)
    assert before[E2EStatus.REPEATED.value] == 8 and before[E2EStatus.CRC_ERROR.value] == 1
    assert after == {"ok": len(messages)}
    assert stats.crcs_fixed == 1
    # HIL frames have no counter and pass as they are.
    sync_before = [bytes(m.data) for m in messages if m.arbitration_id == FrameId.HIL_SYNC]
    sync_after = [bytes(m.data) for m in rewritten if m.arbitration_id == FrameId.HIL_SYNC]
    assert sync_before == sync_after


def test_select_ids_and_parse_ids() -> None:
    messages = read_log(LOGS / "lockstep_lmpc.log").messages
    assert parse_ids("0x100, VEH_POSE_XY,258") == [0x100, 0x101, 0x102]
    kept = select_ids(messages, parse_ids("0x100,PLANNER_REQ"))
    assert {m.arbitration_id for m in kept} == {0x100, 0x110} and len(kept) == 280
    for bad, message in (("0x100,zz", "'zz'"), ("", "no ID"), ("-1", "outside")):
        with pytest.raises(PlayError, match=message):
            parse_ids(bad)


def test_scale_timing() -> None:
    messages = [can.Message(timestamp=10.0 + t) for t in (0.0, 0.1, 0.3)]
    assert [m.timestamp for m in scale_timing(messages, 2.0)] == pytest.approx([10.0, 10.05, 10.15])
    with pytest.raises(PlayError, match="--speed must be > 0"):
        scale_timing(messages, 0.0)


def test_play_sends_every_frame_in_order_with_the_recorded_gaps() -> None:
    messages = read_log(LOGS / "realtime_lmpc.blf").messages[:120]
    duration = messages[-1].timestamp - messages[0].timestamp
    channel = f"play-test-{os.getpid()}"
    sender = can.Bus(interface="virtual", channel=channel)
    receiver = can.Bus(interface="virtual", channel=channel)
    try:
        started = time.monotonic()
        sent = play(messages, sender)
        elapsed = time.monotonic() - started
        received = []
        while (message := receiver.recv(0.0)) is not None:
            received.append(message)
    finally:
        sender.shutdown()
        receiver.shutdown()
    print(f"{sent} frames spanning {duration:.3f} s played in {elapsed:.3f} s")
    assert sent == len(received) == 120
    assert [(m.arbitration_id, bytes(m.data)) for m in received] == \
        [(m.arbitration_id, bytes(m.data)) for m in messages]
    # MessageSync waits out the recorded gaps: never faster than the recording.
    assert elapsed >= 0.9 * duration


def test_play_cli_onto_a_virtual_bus(hil_cli, capsys) -> None:
    channel = f"play-cli-{os.getpid()}"
    receiver = can.Bus(interface="virtual", channel=channel)
    try:
        status = hil_cli(["play", str(LOGS / "faults_lmpc.asc"), "--interface", "virtual",
                          "--channel", channel, "--ids", "VEH_DYN,PLANNER_REQ", "--speed", "50",
                          "--rewrite-e2e"])
        received = []
        while (message := receiver.recv(0.0)) is not None:
            received.append(message)
    finally:
        receiver.shutdown()
    out = capsys.readouterr().out
    print(out)
    assert status == 0 and "sent 275 frames" in out
    assert {m.arbitration_id for m in received} == {0x100, 0x110} and len(received) == 275
    assert _verdicts(received) == {"ok": 275}


def test_play_cli_bad_input(hil_cli, capsys) -> None:
    assert hil_cli(["play", str(LOGS / "lockstep_lmpc.log"), "--interface", "virtual",
                    "--channel", "x", "--ids", "0x555"]) == 1
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and "no frame left to play" in err
    capsys.readouterr()  # the print above
    assert hil_cli(["play", str(LOGS / "lockstep_lmpc.log"), "--interface", "nosuchbus"]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("error: ") and "cannot open CAN bus" in captured.err, captured.err
    assert captured.out == ""  # issue 39 item 7: no "playing N frames" before the error
    assert hil_cli(["play", str(LOGS / "lockstep_lmpc.log"), "--interface", "nosuchbus",
                    "--rewrite-e2e"]) == 1
    assert capsys.readouterr().out == ""

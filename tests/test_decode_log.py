"""hil.decode_log and ``python -m hil decode``: CSV (one row per frame) and the plot."""
from __future__ import annotations

import csv
from pathlib import Path

import can
import numpy as np
import pytest

from can_defs.codec import decode
from can_defs.frames import FrameId
from controller.reference import ReferencePath
from hil.decode_log import SIGNAL_COLUMNS, decode_log, lateral_deviation, write_csv
from hil.logio import read_log

LOGS = Path(__file__).parent / "data" / "logs"
DLC = Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"


@pytest.fixture
def hil_cli(monkeypatch: pytest.MonkeyPatch):
    """``python -m hil`` with the decode subcommand registered."""
    import hil.__main__ as cli

    monkeypatch.setitem(cli.SUBCOMMANDS, "decode", "hil.commands.decode")
    return cli.main


def test_csv_has_one_row_per_frame_with_decoded_signals(tmp_path: Path) -> None:
    contents = read_log(LOGS / "lockstep_lmpc.log")
    decoded = decode_log(contents)
    path = write_csv(decoded, tmp_path / "out.csv")
    with path.open() as handle:
        rows = list(csv.DictReader(handle))
    print(rows[2])
    assert len(rows) == len(contents.messages) == 1643
    assert set(SIGNAL_COLUMNS) <= set(rows[0])
    dyn_rows = [r for r in rows if r["frame"] == "VEH_DYN"]
    dyn_messages = [m for m in contents.messages if m.arbitration_id == FrameId.VEH_DYN]
    for row, message in zip(dyn_rows, dyn_messages):
        frame = decode(message.arbitration_id, bytes(message.data)).frame
        assert float(row["vx"]) == pytest.approx(frame.vx) and row["steer_angle_cmd"] == ""
    # Lockstep: virtual time; plant frames every 10 ms.
    assert [float(r["time_s"]) for r in dyn_rows[:3]] == [0.0, 0.01, 0.02]
    assert {r["e2e"] for r in rows} == {"ok"}


def test_e2e_verdicts_show_the_injected_faults() -> None:
    decoded = decode_log(read_log(LOGS / "faults_lmpc.asc"))
    print(decoded.e2e_counts)
    # Bit flip: one CRC error, the next VEH_POSE_XY counts 1 lost; frozen planner counter:
    # 8 repeats, then the jump back is a sequence error, as are the plant IDs' jumps of 6
    # after five dropped samples.
    assert decoded.e2e_counts["crc_error"] == 1
    assert decoded.e2e_counts["lost"] == 1
    assert decoded.e2e_counts["repeated"] == 8
    assert decoded.e2e_counts["sequence_error"] == 4
    # Rejected frames do not feed the series: of 195 VEH_POSE_XY, the bit-flipped one and
    # the first after the drop (sequence error) are left out.
    times, _ = decoded.series("pos_x", FrameId.VEH_POSE_XY)
    assert times.size == 195 - 2


def test_foreign_frames_keep_their_raw_payload(tmp_path: Path) -> None:
    import can

    messages = [can.Message(timestamp=0.0, arbitration_id=0x3E8, data=b"\xab\xcd", is_extended_id=False),
                can.Message(timestamp=0.01, arbitration_id=0x18FF0001, data=b"\x01")]
    with can.Logger(tmp_path / "f.log") as writer:
        for message in messages:
            writer.on_message_received(message)
    decoded = decode_log(read_log(tmp_path / "f.log"))
    print(decoded.rows)
    assert decoded.rows[0]["frame"] == "(not in DBC)" and decoded.rows[0]["data"] == "abcd"
    assert decoded.rows[0]["e2e"] == "unknown_id"
    assert decoded.rows[1]["frame"] == "(extended frame)"


def test_each_frame_kind_is_named_by_the_one_frame_kind_test(tmp_path: Path) -> None:
    """An 11-bit CAN FD frame is a CAN FD frame, not an extended one; an extended frame is
    extended; a classic 11-bit frame of a contract ID is decoded as that frame."""
    classic = can.Message(timestamp=0.0, arbitration_id=int(FrameId.VEH_DYN), data=bytes(8),
                          is_extended_id=False)
    messages = [classic,
                can.Message(timestamp=0.01, arbitration_id=int(FrameId.VEH_DYN), data=bytes(16),
                            is_extended_id=False, is_fd=True),
                can.Message(timestamp=0.02, arbitration_id=0x18FF0001, data=bytes(12), is_fd=True),
                can.Message(timestamp=0.03, arbitration_id=0x18FF0001, data=b"\x01"),
                can.Message(timestamp=0.04, arbitration_id=int(FrameId.VEH_DYN),
                            is_extended_id=False, is_remote_frame=True, dlc=8),
                can.Message(timestamp=0.05, is_error_frame=True)]
    with can.Logger(tmp_path / "kinds.log") as writer:
        for message in messages:
            writer.on_message_received(message)
    decoded = decode_log(read_log(tmp_path / "kinds.log"))
    print([row["frame"] for row in decoded.rows])
    assert [row["frame"] for row in decoded.rows] == [
        "VEH_DYN", "(CAN FD frame)", "(extended CAN FD frame)", "(extended frame)",
        "(remote frame)", "(error frame)"]
    assert [row["e2e"] for row in decoded.rows][1:] == ["unknown_id"] * 5


def test_lateral_deviation_of_the_recorded_run_is_small() -> None:
    decoded = decode_log(read_log(LOGS / "lockstep_lmpc.log"))
    times, e_y = lateral_deviation(decoded, ReferencePath.from_csv(DLC))
    print(f"{times.size} poses, max |e_Y| = {np.max(np.abs(e_y)):.4f} m")
    assert times.size == 200
    # The run starts on the path (Y(10 m) = 13.5 mm) and the LMPC keeps it within mm.
    assert abs(e_y[0]) < 2e-3 and np.max(np.abs(e_y)) < 0.05


def test_decode_cli_writes_csv_and_plot(hil_cli, capsys, tmp_path: Path) -> None:
    status = hil_cli(["decode", str(LOGS / "realtime_lmpc.blf"), "--csv", str(tmp_path / "d.csv"),
                      "--plot", str(tmp_path / "d.png")])
    out = capsys.readouterr().out
    print(out)
    assert status == 0
    assert "time base: log timestamps" in out
    assert (tmp_path / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "d.png").stat().st_size > 20_000
    # One CSV row per frame of the log as python-can reads it, plus the header.
    with can.BLFReader(LOGS / "realtime_lmpc.blf") as reader:
        frames = sum(1 for _ in reader)
    assert frames > 500  # a 2 s drive
    assert len((tmp_path / "d.csv").read_text().splitlines()) == frames + 1


@pytest.mark.parametrize("args, message", [
    (["decode", "x.pdf"], "unknown log format '.pdf'"),
    (["decode", "absent.blf"], "no such log file"),
    (["decode", str(LOGS / "lockstep_lmpc.log"), "--plot", "p.png", "--path", "1=/no.csv"],
     "cannot read /no.csv"),
])
def test_decode_cli_bad_input(hil_cli, capsys, args: list[str], message: str) -> None:
    assert hil_cli(args) == 1
    err = capsys.readouterr().err
    print(err)
    assert err.startswith("error: ") and message in err and "Traceback" not in err

"""can_defs.log_reader, the one reader of recorded CAN logs: frame kinds (CAN FD
included), candump and gzip handling, and the same frames for both of its users
(hil.logio for replay / decode / play, models.can_log_data for identification)."""
from __future__ import annotations

import gzip
from pathlib import Path

import can
import pytest

from can_defs.codec import FrameSender
from can_defs.frames import FrameId, VehDyn
from can_defs.log_reader import (FrameKind, LogFormatError, LogReadError, csv_header,
                                 frame_kind, is_contract_data_frame, is_python_can_csv,
                                 read_log_frames)
from hil import logio
from models import can_log_data

LOGS = Path(__file__).parent / "data" / "logs"
LOCKSTEP = LOGS / "lockstep_lmpc.log"

#: One line of each kind a candump -L log holds, in this order.
_VEH_DYN = FrameSender().encode(VehDyn(10.0, 0.1, 0.01)).hex().upper()
MIXED_LINES = (
    f"(1700000000.000000) vcan0 100#{_VEH_DYN}",            # classic data, contract ID
    f"(1700000000.001000) vcan0 100##1{_VEH_DYN}00000000",  # CAN FD (BRS), 12 bytes
    "(1700000000.002000) vcan0 123#R8",                      # remote request
    "(1700000000.003000) vcan0 20000080#0000000000000000",   # error frame
    "(1700000000.004000) vcan0 18FF0001#0102",               # extended-ID data
)
MIXED_KINDS = (FrameKind.DATA, FrameKind.FD, FrameKind.REMOTE, FrameKind.ERROR, FrameKind.DATA)


def _write_mixed(path: Path) -> Path:
    text = "".join(line + "\n" for line in MIXED_LINES)
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


def _frames(messages: list[can.Message]) -> list[tuple]:
    return [(m.timestamp, m.arbitration_id, bytes(m.data), frame_kind(m), m.is_extended_id)
            for m in messages]


@pytest.mark.parametrize("name", ["mixed.log", "mixed.log.gz"])
def test_every_frame_kind_of_a_candump_log_is_read_and_told_apart(tmp_path: Path, name: str) -> None:
    log = read_log_frames(_write_mixed(tmp_path / name))
    print([(m.arbitration_id, frame_kind(m).value, len(m.data)) for m in log.messages])
    assert log.complete and not log.warnings and log.skipped_lines == 0
    assert tuple(frame_kind(m) for m in log.messages) == MIXED_KINDS
    fd = log.messages[1]
    assert fd.is_fd and fd.bitrate_switch and len(fd.data) == 12
    # only the classic 11-bit data frame can be one of the contract's
    assert [is_contract_data_frame(m) for m in log.messages] == [True, False, False, False, False]


def test_frame_kind_of_messages_from_any_reader() -> None:
    assert frame_kind(can.Message(arbitration_id=0x100, data=b"\0" * 8)) is FrameKind.DATA
    assert frame_kind(can.Message(arbitration_id=0x100, data=b"\0" * 16, is_fd=True)) is FrameKind.FD
    assert frame_kind(can.Message(arbitration_id=0x100, is_remote_frame=True, dlc=8)) is FrameKind.REMOTE
    assert frame_kind(can.Message(is_error_frame=True, is_fd=True)) is FrameKind.ERROR


def test_gzip_candump_reads_the_same_frames_as_the_plain_file(tmp_path: Path) -> None:
    packed = tmp_path / "lockstep.log.gz"
    packed.write_bytes(gzip.compress(LOCKSTEP.read_bytes()))
    plain, unpacked = read_log_frames(LOCKSTEP), read_log_frames(packed)
    print(len(plain.messages), "frames in both")
    assert unpacked.complete and _frames(unpacked.messages) == _frames(plain.messages)


def test_a_truncated_gzip_keeps_the_whole_lines_before_the_cut(tmp_path: Path) -> None:
    packed = gzip.compress(LOCKSTEP.read_bytes())
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    log = read_log_frames(cut)
    print(len(log.messages), "frames;", log.warnings)
    assert not log.complete and "the gzip stream is truncated" in log.warnings[0]
    whole = read_log_frames(LOCKSTEP).messages
    assert 0 < len(log.messages) < len(whole)
    assert _frames(log.messages) == _frames(whole[: len(log.messages)])


def test_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match=r"run\.mdf: unknown log format '\.mdf'"):
        read_log_frames(tmp_path / "run.mdf")
    with pytest.raises(LogReadError, match=r"absent\.log: no such log file"):
        read_log_frames(tmp_path / "absent.log")
    (tmp_path / "noise.log").write_text("hello\n")
    with pytest.raises(LogReadError, match=r"noise\.log: no readable CAN frame \(1 line"):
        read_log_frames(tmp_path / "noise.log")


def test_check_file_runs_before_any_reader(tmp_path: Path) -> None:
    seen: list[Path] = []
    read_log_frames(LOCKSTEP, check_file=seen.append)
    assert seen == [LOCKSTEP]


def test_csv_header_of_plain_and_gzip_files(tmp_path: Path) -> None:
    header = "timestamp, arbitration_id, extended, remote, error, dlc, data"
    plain = tmp_path / "log.csv"
    plain.write_text(header + "\r\n1,2,3\n")
    packed = tmp_path / "log.csv.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    named = tmp_path / "export.csv"
    named.write_text("t,speed\n0,1\n")
    assert csv_header(plain) == csv_header(packed) == header
    assert is_python_can_csv(plain) and is_python_can_csv(packed) and not is_python_can_csv(named)


@pytest.mark.parametrize("suffix", [".log", ".log.gz", ".blf", ".asc"])
def test_both_users_read_the_same_frames(tmp_path: Path, suffix: str) -> None:
    if suffix.startswith(".log"):
        path = _write_mixed(tmp_path / f"mixed{suffix}")
    else:
        path = tmp_path / f"copy{suffix}"
        with can.Logger(path) as writer:
            for message in read_log_frames(LOCKSTEP).messages:
                writer.on_message_received(message)
    for_replay = logio.read_log(path)
    for_identification, warning = can_log_data.read_frames(path)
    print(suffix, len(for_replay.messages), "frames; warnings", for_replay.warnings, warning)
    assert _frames(for_identification) == _frames(for_replay.messages)
    assert warning is None and for_replay.complete


def test_can_fd_frames_are_no_contract_frames_for_either_user(tmp_path: Path) -> None:
    path = _write_mixed(tmp_path / "mixed.log")
    contents = logio.read_log(path)
    print("\n".join(contents.summary_lines()))
    assert contents.frames_by_id == {int(FrameId.VEH_DYN): 1}
    assert (contents.fd_frames, contents.remote_frames, contents.error_frames,
            contents.extended_frames) == (1, 1, 1, 1)
    assert "  CAN FD frames: 1" in contents.summary_lines()
    counts = can_log_data.LogCounts()
    can_log_data._decode_streams(can_log_data.read_frames(path)[0], counts)
    assert (counts.frames, counts.not_contract, counts.plant_frames) == (5, 4, 1)


def _vector_copy(path: Path) -> Path:
    """The lockstep test log written by python-can's writer of ``path``'s suffix."""
    with can.Logger(path) as writer:
        for message in read_log_frames(LOCKSTEP).messages:
            writer.on_message_received(message)
    return path


@pytest.mark.parametrize("suffix, keep", [(".blf", 3000), (".blf", 100_000), (".asc", 9000),
                                          (".blf.gz", 3000), (".asc.gz", 9000)])
def test_a_cut_blf_or_asc_is_incomplete_and_keeps_the_frames_before_the_cut(
        tmp_path: Path, suffix: str, keep: int) -> None:
    whole = _vector_copy(tmp_path / f"whole{suffix.removesuffix('.gz')}")
    raw = whole.read_bytes()
    raw = raw[:keep] if keep < len(raw) else raw[:len(raw) - 100]
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(gzip.compress(raw) if suffix.endswith(".gz") else raw)
    frames = read_log_frames(cut)
    print(frames.warnings)
    assert not frames.complete and len(frames.warnings) >= 1
    assert "BLF file is truncated" in frames.warnings[0] or "line" in frames.warnings[0]
    full = read_log_frames(whole).messages
    assert 0 < len(frames.messages) < len(full)
    assert _frames(frames.messages) == _frames(full[:len(frames.messages)])


def test_the_blf_cut_names_the_header_size_and_object_count(tmp_path: Path) -> None:
    from can_defs.log_reader import blf_cut

    raw = _vector_copy(tmp_path / "whole.blf").read_bytes()
    assert blf_cut(raw).problem is None
    cut = blf_cut(raw[:3000])
    print(cut.problem)
    assert cut.readable == 3000
    assert f"the file header says {len(raw)} bytes" in cut.problem
    assert blf_cut(raw[:150]).readable == 144  # inside an object header: the reader stops there


def test_an_asc_without_end_triggerblock_is_incomplete(tmp_path: Path) -> None:
    from can_defs.log_reader import asc_cut

    whole = _vector_copy(tmp_path / "whole.asc").read_text()
    assert asc_cut(whole) == (whole, [])
    without_end = whole[:whole.rindex("End TriggerBlock")]
    text, problems = asc_cut(without_end)
    assert text == without_end and len(problems) == 1 and "End TriggerBlock" in problems[0]
    text, problems = asc_cut(without_end[:-10])
    assert text.endswith("\n") and len(problems) == 2 and "no line end" in problems[0]

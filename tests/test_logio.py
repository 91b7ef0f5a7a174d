"""hil.logio: reading recorded logs of every python-can format, damaged ones included."""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import can
import pytest

from can_defs.codec import encode
from can_defs.frames import FrameId, HilSync, VehDyn
from hil.logio import (LogContents, LogFormatError, LogMetadata, LogReadError, SidecarError,
                       frame_times, read_log, read_sidecar, sidecar_path, write_sidecar)

LOGS = Path(__file__).parent / "data" / "logs"
LOCKSTEP = LOGS / "lockstep_lmpc.log"


def _write(path: Path, messages: list[can.Message]) -> Path:
    with can.Logger(path) as writer:
        for message in messages:
            writer.on_message_received(message)
    return path


def _frames(log: LogContents) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in log.messages]


def test_lockstep_log_counts_every_contract_frame() -> None:
    log = read_log(LOCKSTEP)
    print("\n".join(log.summary_lines()))
    assert log.complete and not log.warnings
    assert log.is_lockstep and log.has_ecu_frames
    # 2 s of lockstep: handshake + 400 ticks, plant every 10 ms, planner/ECU every 25 ms,
    # and the ECU's shutdown command.
    assert log.frames_by_id[FrameId.HIL_SYNC] == 401
    assert log.frames_by_id[FrameId.HIL_SYNC_ACK] == 401
    assert log.frames_by_id[FrameId.VEH_DYN] == 200
    assert log.frames_by_id[FrameId.PLANNER_REQ] == 80
    assert log.frames_by_id[FrameId.STEER_TORQUE_CMD] == 81
    assert not log.unknown_ids


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".csv", ".trc", ".log.gz", ".asc.gz"])
def test_every_format_round_trips_the_frames(tmp_path: Path, suffix: str) -> None:
    original = read_log(LOCKSTEP)
    copy = read_log(_write(tmp_path / f"copy{suffix}", original.messages))
    print(f"{suffix}: {len(copy.messages)} frames, warnings {copy.warnings}")
    assert _frames(copy) == _frames(original)
    assert copy.frames_by_id == original.frames_by_id
    # Virtual time comes from the TICKs, so it survives formats with relative timestamps.
    assert frame_times(copy.messages)[0] == frame_times(original.messages)[0]


def test_shipped_logs_in_other_formats_are_read() -> None:
    blf = read_log(LOGS / "realtime_lmpc.blf")
    asc = read_log(LOGS / "faults_lmpc.asc")
    print(blf.summary_lines()[1], asc.summary_lines()[1], sep="\n")
    assert not blf.is_lockstep and blf.frames_by_id[FrameId.VEH_DYN] == 200
    assert asc.is_lockstep and asc.frames_by_id[FrameId.VEH_DYN] == 195  # 5 dropped


def test_unknown_suffix_is_a_format_error(tmp_path: Path) -> None:
    path = tmp_path / "run.xyz"
    path.write_text("(0.0) vcan0 100#00\n")
    with pytest.raises(LogFormatError, match=r"unknown log format '\.xyz'.*\.log"):
        read_log(path)


def test_missing_and_empty_files_are_read_errors(tmp_path: Path) -> None:
    with pytest.raises(LogReadError, match="no such log file"):
        read_log(tmp_path / "absent.log")
    (tmp_path / "empty.blf").write_bytes(b"")
    with pytest.raises(LogReadError, match="empty.blf"):
        read_log(tmp_path / "empty.blf")
    (tmp_path / "garbage.log").write_text("hello\nworld\n")
    with pytest.raises(LogReadError, match="2 line"):
        read_log(tmp_path / "garbage.log")


def test_damaged_candump_lines_are_skipped_and_counted(tmp_path: Path) -> None:
    lines = LOCKSTEP.read_text().splitlines()
    damaged = lines[:100] + ["(1795316788.1) vcan0 10", "garbage line"] + lines[100:200]
    damaged.append(lines[200][:17])  # truncated mid-timestamp, as a killed recorder leaves it
    path = tmp_path / "damaged.log"
    path.write_text("\n".join(damaged))
    log = read_log(path)
    print(log.warnings)
    assert len(log.messages) == 200
    assert log.skipped_lines == 2 and not log.complete
    assert "last line (203) is incomplete" in log.warnings[0]
    assert "2 line(s)" in log.warnings[1] and "line 101, 102" in log.warnings[1]
    # A cut line that still looks like a shorter frame is caught by its missing line end.
    path.write_text("\n".join(lines[:10]) + "\n" + lines[10][:-12])
    log = read_log(path)
    assert len(log.messages) == 10 and "incomplete" in log.warnings[0]


def test_truncated_blf_gives_a_partial_result_with_a_warning(tmp_path: Path) -> None:
    original = read_log(LOCKSTEP)
    whole = _write(tmp_path / "whole.blf", original.messages).read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(whole[: len(whole) // 2])
    log = read_log(cut)
    print(f"{len(log.messages)} of {len(original.messages)} frames; {log.warnings}")
    assert 0 < len(log.messages) < len(original.messages)
    assert _frames(log) == _frames(original)[: len(log.messages)]


def test_truncated_gzip_gives_a_partial_result(tmp_path: Path) -> None:
    packed = gzip.compress(LOCKSTEP.read_bytes())
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    log = read_log(cut)
    print(f"{len(log.messages)} frames; {log.warnings}")
    assert 0 < len(log.messages) < 1643 and not log.complete


def test_truncated_asc_keeps_the_frames_before_the_cut(tmp_path: Path) -> None:
    original = read_log(LOCKSTEP)
    text = _write(tmp_path / "whole.asc", original.messages).read_text()
    cut = tmp_path / "cut.asc"
    cut.write_text(text[: len(text) // 3])
    log = read_log(cut)
    print(f"{len(log.messages)} frames; {log.warnings}")
    assert 0 < len(log.messages) < len(original.messages)
    assert _frames(log)[:-1] == _frames(original)[: len(log.messages) - 1]


def test_foreign_extended_remote_and_error_frames_are_counted(tmp_path: Path) -> None:
    messages = [
        can.Message(timestamp=0.0, arbitration_id=0x100, data=encode(VehDyn(10.0, 0.0, 0.0)),
                    is_extended_id=False),
        can.Message(timestamp=0.001, arbitration_id=0x3E8, data=b"\x01", is_extended_id=False),
        can.Message(timestamp=0.002, arbitration_id=0x3E8, data=b"\x02", is_extended_id=False),
        can.Message(timestamp=0.003, arbitration_id=0x7FF, data=b"", is_extended_id=False),
        can.Message(timestamp=0.004, arbitration_id=0x18FF0001, data=b"\x00" * 8),
        can.Message(timestamp=0.005, arbitration_id=0x123, is_remote_frame=True, dlc=8,
                    is_extended_id=False),
        can.Message(timestamp=0.006, is_error_frame=True),
    ]
    log = read_log(_write(tmp_path / "mixed.log", messages))
    print("\n".join(log.summary_lines()))
    assert log.frames_by_id == {0x100: 1}
    assert log.unknown_ids == {0x3E8: 2, 0x7FF: 1}
    assert (log.extended_frames, log.remote_frames, log.error_frames) == (1, 1, 1)
    assert any("outside the DBC: 3" in line for line in log.summary_lines())


def _msg(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def test_frame_times_follow_the_lockstep_protocol() -> None:
    sync = lambda tick: _msg(FrameId.HIL_SYNC, encode(HilSync(tick)))  # noqa: E731
    ack = lambda tick: _msg(FrameId.HIL_SYNC_ACK, encode(HilSync(tick)))  # noqa: E731
    plant = _msg(FrameId.VEH_DYN, encode(VehDyn(1.0, 0.0, 0.0)))
    command = _msg(FrameId.STEER_TORQUE_CMD, bytes(8))
    messages = [sync(0xFFFFFFFF), ack(0xFFFFFFFF), plant, sync(0), command, ack(0),
                plant, sync(5), ack(5), command]
    times, base = frame_times(messages)
    print(times, base)
    # Inputs belong to the next TICK, the ECU's frames to the TICK they answered.
    assert times == [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.005, 0.005, 0.005, 0.005]
    assert "HIL_SYNC" in base


def test_frame_times_without_sync_are_relative_timestamps() -> None:
    messages = [can.Message(timestamp=100.0 + dt, arbitration_id=0x100, data=bytes(8))
                for dt in (0.0, 0.01, 0.02)]
    times, base = frame_times(messages)
    assert times == pytest.approx([0.0, 0.01, 0.02]) and "timestamps" in base


def test_sidecar_round_trip_stores_repository_paths_relative(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    repo_path = Path(__file__).resolve().parent.parent / "hil" / "paths" / "dlc.csv"
    target = write_sidecar(log, LogMetadata("lmpc", "lockstep", {1: str(repo_path)}, "dlc_smoke"))
    assert target == sidecar_path(log) == tmp_path / "run.log.json"
    stored = json.loads(target.read_text())
    print(stored)
    assert stored["paths"] == {"1": "hil/paths/dlc.csv"}
    metadata = read_sidecar(log)
    assert metadata is not None and metadata.controller == "lmpc"
    assert Path(metadata.paths[1]).resolve() == repo_path
    assert read_sidecar(tmp_path / "other.log") is None


@pytest.mark.parametrize("content, field", [
    ("{not json", "not readable JSON"),
    ('{"controller": 3}', "'controller'"),
    ('{"controller": "lmpc", "mode": "fast"}', "'mode'"),
    ('{"controller": "lmpc", "paths": {"x": "a.csv"}}', "PATH_ID 'x'"),
])
def test_malformed_sidecar_names_the_field(tmp_path: Path, content: str, field: str) -> None:
    (tmp_path / "run.log.json").write_text(content)
    with pytest.raises(SidecarError, match=field):
        read_sidecar(tmp_path / "run.log")


def test_sidecar_records_the_ecu_its_model_excitation_and_input_hashes(tmp_path: Path) -> None:
    from hil.logio import check_input_files, describe_inputs

    root = Path(__file__).resolve().parent.parent
    model = tmp_path / "bicycle.json"
    model.write_text("{}")
    program = tmp_path / "program.toml"
    program.write_text("kind = 'prbs'\n")
    inputs = describe_inputs([("path 1", root / "hil" / "paths" / "dlc.csv"), ("model", model),
                              ("excite", program)])
    log = tmp_path / "run.log"
    write_sidecar(log, LogMetadata("lmpc", "lockstep", {1: str(root / "hil/paths/dlc.csv")},
                                   ecu="python", model=str(model), excite=str(program),
                                   input_files=inputs))
    stored = json.loads(sidecar_path(log).read_text())
    assert stored["version"] == 3 and stored["ecu"] == "python"
    assert stored["input_files"][0] == {"role": "path 1", "file": "hil/paths/dlc.csv",
                                        "sha256": inputs[0].sha256}
    metadata = read_sidecar(log)
    assert metadata is not None and metadata.model == str(model) and metadata.excite == str(program)
    assert check_input_files(metadata.input_files) == []
    model.write_text("{ }")
    program.unlink()
    problems = [sentence for _, sentence in check_input_files(metadata.input_files)]
    assert len(problems) == 2
    assert f"the model file {model} changed since the recording" in problems[0]
    assert problems[1] == f"the excite file {program} is missing"
    assert check_input_files(metadata.input_files, skip_roles=("model", "excite")) == []


def test_an_old_sidecar_has_no_ecu_inputs(tmp_path: Path) -> None:
    (tmp_path / "run.log.json").write_text(
        '{"version": 2, "controller": "lmpc", "paths": {"1": "hil/paths/dlc.csv"}}')
    metadata = read_sidecar(tmp_path / "run.log")
    assert metadata is not None and (metadata.ecu, metadata.model, metadata.excite) == (None,) * 3
    assert metadata.input_files == ()

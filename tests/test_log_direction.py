"""Direction in recorded logs (issue 39): from the ECU's point of view, its own
transmissions (per the DBC's transmitter node) are Tx and every other frame Rx, in every
format that records a direction, as python-can's readers and cantools see it; the
project's readers find the ECU's frames by ID, so old logs (every frame Rx) and new ones
read, replay and identify the same."""
from __future__ import annotations

import subprocess
import sys
import uuid
from pathlib import Path

import can
import numpy as np
import pytest

from can_defs.codec import FrameSender
from can_defs.frames import CtrlDiag, CtrlMode, FrameId, HilSync, HilSyncAck, QpStatus, SteerTorqueCmd, VehDyn
from hil.logio import frame_times, read_log, read_sidecar
from hil.recorder import BusRecorder, transmitted_ids
from models import can_log_data

LOGS = Path(__file__).parent / "data" / "logs"
LOCKSTEP = LOGS / "lockstep_lmpc.log"
DBC = Path(__file__).parent.parent / "can_defs" / "vehicle.dbc"

#: Formats that record a direction (python-can's writers and readers), and those that do not.
WITH_DIRECTION = [".log", ".log.gz", ".asc", ".blf", ".trc", ".mf4"]
WITHOUT_DIRECTION = [".csv", ".db"]

_SENDER = FrameSender()


def _data(frame_id: int, payload: bytes, **flags: bool) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=payload, is_extended_id=False, **flags)


#: (who sends it, the frame, whether the log must mark it received).
TRAFFIC = (
    ("plant", _data(FrameId.VEH_DYN, _SENDER.encode(VehDyn(10.0, 0.1, 0.01))), True),
    ("master", _data(FrameId.HIL_SYNC, _SENDER.encode(HilSync(5))), True),
    ("ecu", _data(FrameId.HIL_SYNC_ACK, _SENDER.encode(HilSyncAck(5))), False),
    ("ecu", _data(FrameId.STEER_TORQUE_CMD, _SENDER.encode(
        SteerTorqueCmd(CtrlMode.ACTIVE, True, -0.05, 120.0))), False),
    ("ecu", _data(FrameId.CTRL_DIAG, _SENDER.encode(
        CtrlDiag(QpStatus.SOLVED, 100, 200, 5, 0, 0))), False),
    # not the ECU's although its ID is: a remote request, an extended ID
    ("plant", can.Message(arbitration_id=FrameId.STEER_TORQUE_CMD, is_remote_frame=True,
                          is_extended_id=False, dlc=8), True),
    ("plant", can.Message(arbitration_id=FrameId.STEER_TORQUE_CMD, data=b"\x01\x02",
                          is_extended_id=True), True),
)


def _record(path: Path) -> None:
    """TRAFFIC sent by three bus objects on one virtual channel, recorded by a fourth."""
    channel = f"direction-{uuid.uuid4().hex}"
    recorder = BusRecorder(can.Bus(interface="virtual", channel=channel), path)
    with recorder, can.Bus(interface="virtual", channel=channel) as ecu, \
            can.Bus(interface="virtual", channel=channel) as others:
        for sender, message, _ in TRAFFIC:
            (ecu if sender == "ecu" else others).send(message)
        assert recorder.wait_for(len(TRAFFIC))


def test_the_ecu_transmits_what_the_dbc_says() -> None:
    assert transmitted_ids() == {FrameId.HIL_SYNC_ACK, FrameId.STEER_TORQUE_CMD,
                                 FrameId.CTRL_DIAG}
    assert transmitted_ids("PLANT") == {FrameId.VEH_DYN, FrameId.VEH_POSE_XY,
                                        FrameId.VEH_POSE_YAW}


@pytest.mark.parametrize("suffix", WITH_DIRECTION + WITHOUT_DIRECTION)
def test_every_format_records_the_direction_python_can_reads_back(tmp_path: Path,
                                                                   suffix: str) -> None:
    log = tmp_path / f"run{suffix}"
    _record(log)
    read = list(can.LogReader(log))  # python-can's own reader, as a third-party tool
    got = [(m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_rx) for m in read]
    print(suffix, got)
    # python-can's TRC writer leaves remote frames out (with a warning)
    kept = [t for t in TRAFFIC if not (suffix == ".trc" and t[1].is_remote_frame)]
    assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for m in read] == \
        [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for _, m, _ in kept]
    if suffix in WITH_DIRECTION:
        assert [m.is_rx for m in read] == [rx for *_, rx in kept]
    else:  # no direction column: python-can reads every frame as received
        assert all(m.is_rx for m in read)
    # the project's reader keeps what the format says
    assert [m.is_rx for m in read_log(log).messages] == [m.is_rx for m in read]


def test_candump_lines_say_t_and_cantools_decodes_them(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    _record(log)
    lines = log.read_text().splitlines()
    print("\n".join(lines))
    assert [line.split()[-1] for line in lines] == ["T" if not rx else "R" for *_, rx in TRAFFIC]
    decoded = subprocess.run([sys.executable, "-m", "cantools", "decode", str(DBC)],
                             input="\n".join(lines[:5]) + "\n", capture_output=True, text=True,
                             check=True).stdout
    print(decoded)
    assert "200#" in decoded and " T ::\nSTEER_TORQUE_CMD(" in decoded
    assert " R ::\nVEH_DYN(" in decoded


def _with_directions(path: Path, marked: bool = True) -> Path:
    """A copy of the shipped lockstep log as the recorder now writes it (``marked``: the
    ECU's frames Tx) or as older recorders did (every frame Rx)."""
    tx = transmitted_ids()
    with can.Logger(path) as writer:
        for message in read_log(LOCKSTEP).messages:
            message.is_rx = not marked or message.arbitration_id not in tx
            writer.on_message_received(message)
    path.with_name(path.name + ".json").write_text(
        (LOGS / "lockstep_lmpc.log.json").read_text())
    return path


def _frames(messages: list[can.Message]) -> list[tuple]:
    return [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in messages]


def test_old_and_new_logs_read_and_identify_the_same(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    marked = _with_directions(tmp_path / "marked.log")
    unmarked = _with_directions(tmp_path / "unmarked.log", marked=False)
    old, new = read_log(unmarked), read_log(marked)
    print("old", sum(not m.is_rx for m in old.messages), "Tx frames; new",
          sum(not m.is_rx for m in new.messages))
    assert all(m.is_rx for m in old.messages) and not all(m.is_rx for m in new.messages)
    assert _frames(new.messages) == _frames(old.messages)
    assert new.frames_by_id == old.frames_by_id and new.has_ecu_frames
    assert frame_times(new.messages) == frame_times(old.messages)
    monkeypatch.setattr(can_log_data, "MIN_SEGMENT_S", 1.0)  # the log is a 2 s drive
    datasets = [can_log_data.load_logs([log], min_data_s=0.5) for log in (unmarked, marked)]
    assert len(datasets[0].trajectories) == len(datasets[1].trajectories) > 0
    for a, b in zip(datasets[0].trajectories, datasets[1].trajectories):
        assert np.array_equal(a.states, b.states) and np.array_equal(a.inputs, b.inputs)


@pytest.mark.slow
def test_a_log_with_directions_replays_as_match(tmp_path: Path) -> None:
    pytest.importorskip("osqp")
    from hil.replay import run_replay

    marked = _with_directions(tmp_path / "marked.log")
    metadata = read_sidecar(marked)
    report = run_replay(read_log(marked), metadata.controller, dict(metadata.paths))
    print(report.text())
    assert report.match and report.comparison.paired == report.comparison.expected > 100


@pytest.mark.parametrize("suffix", [".mf4", ".blf"])
def test_a_binary_log_keeps_frames_whose_channel_name_ends_in_a_large_number(tmp_path: Path, suffix: str) -> None:
    """MF4 and BLF store the bus channel in one and two bytes, taken by python-can from the
    trailing digits of the channel name: names ending in 8454 and 409955 once made the
    writers drop the frame."""
    log = tmp_path / f"run{suffix}"
    channel = f"direction-{uuid.uuid4().hex}-409955"
    recorder = BusRecorder(can.Bus(interface="virtual", channel=channel), log)
    with recorder, can.Bus(interface="virtual", channel=channel) as others:
        others.send(TRAFFIC[0][1])
        assert recorder.wait_for(1)
    assert [m.arbitration_id for m in can.LogReader(log)] == [FrameId.VEH_DYN]

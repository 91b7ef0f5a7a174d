"""Revision 2 of the contract in the ECU, and the ECU's defects of issue 17, each
reproduced the way the issue found it: frame kinds (CAN FD handshake, defect 10),
plausibility of plant samples (defect 11), jumps of virtual time (defect 9), a lost bus
(defect 8), rate-limited log lines, and the start-up checks of the ECU's command line
(pipe as path file, defect 1; broken DBC, defect 2; unwritable timing file, defect 3;
nonsense path files, defect 4)."""
from __future__ import annotations

import logging
import math
import os
import resource
import shutil
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from can_defs.codec import encode
from can_defs.frames import HANDSHAKE_TICK, CtrlMode, FrameId, HilSync, VehDyn

from firmware_sim import cli, path_arguments
from firmware_sim.ecu import Ecu
from firmware_sim.ratelimit import RateLimitedLog
from hil.ecu_harness import PeerNodes, ScriptedController, commands, diags, pump
from test_ecu_lockstep import Rig, ack_ticks, buses, engaged, moving_plant  # noqa: F401 (fixture)

REPO = Path(__file__).resolve().parents[1]
DLC = REPO / "hil" / "paths" / "dlc.csv"


def engaged_rig(buses) -> Rig:
    rig = Rig(*buses)
    rig.handshake()
    rig.run(0, 100)
    assert rig.command_at(100).ctrl_mode is CtrlMode.ACTIVE
    return rig


# ------------------------------------------------------------------ frame kinds (defect 10)
@pytest.mark.parametrize("kind", ["fd", "extended", "remote", "error"])
def test_non_classic_handshake_look_alike_never_resets_a_running_ecu(buses, kind):
    """Issue 17, defect 10: a CAN FD frame carrying the handshake value reset a running ECU."""
    rig = engaged_rig(buses)
    message = can.Message(arbitration_id=int(FrameId.HIL_SYNC), data=encode(HilSync(HANDSHAKE_TICK)),
                          is_fd=kind == "fd", is_extended_id=kind == "extended",
                          is_remote_frame=kind == "remote", is_error_frame=kind == "error")
    rig.peers.bus.send(message)
    pump(rig.ecu, rig.ecu_bus)
    answered = rig.peers.received()
    sent = rig.tick(105)
    print(kind, "answer to the look-alike:", answered, "| ignored:", rig.ecu.ignored_frames)
    assert answered == [] and rig.ecu.ignored_frames == 1
    assert ack_ticks(sent) == [105] and rig.ecu.mode is CtrlMode.ACTIVE
    rig.tick(110)
    rig.tick(115)
    rig.tick(120)
    diag = rig.tick(125)
    assert rig.command_at(125).ctrl_mode is CtrlMode.ACTIVE
    assert diags(diag)[0].faults == 0  # never a FAULTS bit


def test_fd_and_extended_plant_look_alikes_are_not_plant_frames(buses):
    rig = engaged_rig(buses)
    data = encode(VehDyn(300.0, 0.0, 0.0), 0)
    rig.peers.bus.send(can.Message(arbitration_id=int(FrameId.VEH_DYN), data=data, is_fd=True))
    rig.peers.bus.send(can.Message(arbitration_id=int(FrameId.VEH_DYN), data=data,
                                   is_extended_id=True))
    rig.run(105, 150)
    print("rx counts:", rig.ecu.rx_counts, "ignored:", rig.ecu.ignored_frames)
    assert rig.ecu.ignored_frames == 2 and rig.ecu.mode is CtrlMode.ACTIVE
    assert diags(rig.log[150])[0].faults == 0


# ------------------------------------------------------------------ plausibility (defect 11)
@pytest.mark.parametrize("values, why", [
    ({"vx": 327.0}, "VX"),
    ({"yaw": 3.2}, "YAW"),
    ({"vy": -11.0}, "VY"),
    ({"yaw_rate": 2.6}, "YAW_RATE"),
    ({"x": 2000.0}, "position"),
])
def test_implausible_plant_samples_are_not_used(buses, caplog, values, why):
    """Issue 17, defect 11: values far outside physics with a valid CRC were used as they
    were. Now such a sample is not a good sample: FAULTS bit 0, DEGRADED, then SAFE_STOP."""
    rig = engaged_rig(buses)
    used_before = len(rig.controller.samples)

    def implausible(t: int) -> dict:
        return {**moving_plant(t), **values}
    with caplog.at_level(logging.WARNING, logger="firmware_sim"):
        rig.run(105, 250, plant=implausible)
    modes = [rig.command_at(t).ctrl_mode for t in (125, 150, 225)]
    samples = rig.controller.samples[used_before:]
    print(why, "modes:", [m.name for m in modes], "| x of the samples used:",
          sorted({round(s.x, 2) for s in samples}), "| counts:", rig.ecu.rx_counts)
    assert all(abs(s.vx) < 70 and abs(s.x) < 100 for s in samples)
    assert modes[:2] == [CtrlMode.DEGRADED, CtrlMode.DEGRADED] and modes[2] is CtrlMode.SAFE_STOP
    assert diags(rig.log[125])[0].faults & 0b0001
    lines = [r for r in caplog.records if "not plausible" in r.getMessage()]
    # a position jump stops being one after 100 ms: that sample restarts the reference,
    # which the ECU meets in SAFE_STOP (re-engaged only through STANDBY)
    expected = 10 if why == "position" else 15
    assert rig.ecu.rx_counts["implausible"] == expected and len(lines) == 1  # rate-limited


def test_plausible_motion_and_restart_after_a_gap_are_accepted(buses):
    """The continuity check applies only while the last good sample is at most 100 ms old;
    after a longer gap a sample elsewhere becomes the new reference (re-engage via STANDBY)."""
    rig = engaged_rig(buses)
    rig.run(105, 300, plant=None)                      # plant silent: SAFE_STOP
    assert rig.command_at(300).ctrl_mode is CtrlMode.SAFE_STOP
    rig.run(305, 400, plant=lambda t: {"vx": 0.0, "x": 500.0, "y": 3.0},
            planner=lambda t: {"engage": False, "target_speed": 0.0, "path_id": 1})
    assert rig.command_at(400).ctrl_mode is CtrlMode.STANDBY
    rig.run(405, 500, plant=lambda t: {"vx": 0.0, "x": 500.0, "y": 3.0})
    assert rig.command_at(500).ctrl_mode is CtrlMode.ACTIVE
    assert rig.ecu.rx_counts["implausible"] == 0


# ------------------------------------------------------------------ jumps of virtual time (defect 9)
def test_jump_of_virtual_time_is_adopted_without_catch_up(buses, caplog):
    """Issue 17, defect 9: HIL_SYNC far ahead ran 40 catch-up tasks on one sample, then
    every later tick counted as going backwards, one warning per tick. Rev. 2: adopted,
    STANDBY, FAULTS bits 1 and 3, no skipped tasks run; the run goes on from the new TICK."""
    rig = engaged_rig(buses)
    steps_before = len(rig.controller.samples)
    resets_before = rig.controller.resets
    with caplog.at_level(logging.WARNING, logger="firmware_sim"):
        jump = rig.tick(60_000, plant=lambda t: moving_plant(100))
        for t in range(59_000, 59_100, 5):   # old ticks afterwards: discarded, logged once
            rig.peers.send_sync(t)
            pump(rig.ecu, rig.ecu_bus)
        stale_answers = rig.peers.received()
        after = rig.run(60_005, 60_200, plant=lambda t: moving_plant(t - 59_900))
    print("jump answered with", [type(m).__name__ for m in jump], "| modes after:",
          [c.ctrl_mode.name for c in commands(after)])
    assert len(commands(jump)) == 1 and ack_ticks(jump) == [60_000]
    assert commands(jump)[0].ctrl_mode is CtrlMode.STANDBY and not commands(jump)[0].cmd_valid
    assert diags(jump)[0].faults & 0b1010 == 0b1010
    assert len(rig.controller.samples) >= steps_before  # nothing stepped at the jump
    assert rig.controller.resets > resets_before
    assert stale_answers == []
    assert ack_ticks(after) == list(range(60_005, 60_201, 5))
    assert commands(after)[-1].ctrl_mode is CtrlMode.ACTIVE  # re-engaged by the usual rule
    backwards = [r for r in caplog.records if "older than the last TICK" in r.getMessage()]
    assert len(backwards) == 1


def test_fault_stays_fault_across_a_jump(buses):
    ecu_bus, peer_bus = buses
    ecu = Ecu(ecu_bus, "scripted", {1: Path("x.csv")}, lockstep=True,
              controller_factory=lambda name: ScriptedController(),
              path_loader=lambda path: (_ for _ in ()).throw(ValueError("bad file")))
    peers = PeerNodes(peer_bus)
    peers.send_handshake()
    peers.send_sync(0)
    peers.send_sync(5000)
    pump(ecu, ecu_bus)
    sent = peers.received()
    assert [c.ctrl_mode for c in commands(sent)] == [CtrlMode.FAULT, CtrlMode.FAULT]


# ------------------------------------------------------------------ a lost bus (defect 8)
class ClosingSocketcand:
    """A socketcand server that accepts python-can's handshake and then closes (a lost bus)."""

    def __init__(self) -> None:
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self.client: socket.socket | None = None

    def serve(self) -> None:
        self._server.settimeout(10.0)
        self.client, _ = self._server.accept()
        self.client.sendall(b"< hi >")
        self.client.recv(256)
        self.client.sendall(b"< ok >")
        self.client.recv(256)
        self.client.sendall(b"< ok >")

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        self._server.close()


@pytest.mark.parametrize("lockstep", [True, False])
def test_lost_bus_is_noticed_without_a_busy_loop(caplog, lockstep):
    """Issue 17, defect 8: when the socketcand server closed, the ECU never noticed and spun
    one core at 100 % (and in real time logged ~80 warnings a second). Now: noticed, logged
    at most once a second, reopened every second, no busy loop."""
    server = ClosingSocketcand()
    serving = threading.Thread(target=server.serve)
    serving.start()
    bus = can.Bus(interface="socketcand", channel="vcan0", host="127.0.0.1", port=server.port)
    serving.join()
    reopen_attempts = []

    def reopen() -> can.BusABC:
        reopen_attempts.append(time.monotonic())
        raise can.CanError("connection refused")
    ecu = Ecu(bus, "scripted", {1: Path("x.csv")}, lockstep=lockstep,
              controller_factory=lambda name: ScriptedController(), path_loader=str,
              reopen_bus=reopen)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,))
    with caplog.at_level(logging.INFO, logger="firmware_sim"):
        thread.start()
        time.sleep(0.3)
        server.close()                    # the server goes away
        cpu_before = resource.getrusage(resource.RUSAGE_SELF)
        wall_before = time.monotonic()
        time.sleep(2.5)
        cpu_after = resource.getrusage(resource.RUSAGE_SELF)
        wall = time.monotonic() - wall_before
        stop.set()
        thread.join(5.0)
        ecu.close()
    cpu = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    lines = [r.getMessage() for r in caplog.records
             if r.levelno >= logging.WARNING and r.name.startswith("firmware_sim")]
    print(f"cpu {cpu:.2f} s in {wall:.2f} s wall; lost {ecu.bus_lost}; reopen attempts "
          f"{len(reopen_attempts)}; log lines {len(lines)}: {lines[:4]}")
    assert not thread.is_alive() and ecu.bus_lost
    assert cpu < 0.5 * wall
    assert 1 <= len(reopen_attempts) <= 3
    lost_lines = [line for line in lines if "bus lost" in line or "still lost" in line]
    assert 1 <= len(lost_lines) <= wall + 1   # at most once a second
    assert len(lines) <= 3 * (wall + 1)      # receive, send, lost: each at most once a second


class _DeadBus:
    """A bus whose every receive fails (an interface that went down)."""

    def __init__(self) -> None:
        self.shut = False

    def recv(self, timeout: float | None = None) -> None:
        raise can.CanOperationError("interface down")

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("interface down")

    def shutdown(self) -> None:
        self.shut = True


def test_lost_bus_is_reopened():
    """Receive errors for 100 ms are a lost bus; the ECU reopens it (every second) and
    answers on the new one."""
    channel = f"ecu-rev2-reopen-{uuid.uuid4()}"
    peer_bus = can.Bus(interface="virtual", channel=channel)
    opened: list[can.BusABC] = []

    def reopen() -> can.BusABC:
        opened.append(can.Bus(interface="virtual", channel=channel))
        return opened[-1]
    dead = _DeadBus()
    ecu = Ecu(dead, "scripted", {1: Path("x.csv")}, lockstep=True,  # type: ignore[arg-type]
              controller_factory=lambda name: ScriptedController(), path_loader=str,
              reopen_bus=reopen)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,))
    thread.start()
    try:
        deadline = time.monotonic() + 5.0
        while not opened and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.1)
        peers = PeerNodes(peer_bus)
        peers.send_handshake()
        answer: list[can.Message] = []
        deadline = time.monotonic() + 3.0
        while not answer and time.monotonic() < deadline:
            answer = peers.received()
            time.sleep(0.02)
    finally:
        stop.set()
        thread.join(5.0)
        ecu.close()
        peer_bus.shutdown()
    print("reopened:", ecu.bus_reopened, "answer after reopening:", answer)
    assert dead.shut and ecu.bus_reopened == 1 and ack_ticks(answer) == [HANDSHAKE_TICK]


# ------------------------------------------------------------------ rate-limited log lines
def test_rate_limited_log_counts_what_it_suppressed(caplog):
    now = [0.0]
    log = RateLimitedLog(logging.getLogger("firmware_sim.test"), clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="firmware_sim.test"):
        for step in range(100):            # every 25 ms for 2.5 s
            now[0] = step * 0.025
            log.log("send", logging.WARNING, "send failed: %s", "bus down")
    lines = [r.getMessage() for r in caplog.records]
    print(lines)
    assert len(lines) == 3 and "(39 more like this" in lines[1]
    assert log.counts["send"] == 100


# ------------------------------------------------------------------ the command line
def test_path_from_a_pipe_is_not_consumed_by_the_argument_check():
    """Issue 17, defect 1: ``--path 1=<(cat hil/paths/dlc.csv)``: the readability check read
    the start of the stream and the ECU latched FAULT about the header."""
    from controller.reference import ReferencePath
    read_end, write_end = os.pipe()
    writer = threading.Thread(target=lambda: (os.write(write_end, DLC.read_bytes()),
                                              os.close(write_end)))
    writer.start()
    try:
        path_id, file = path_arguments.parse_path_argument(f"1=/dev/fd/{read_end}")
        path = ReferencePath.from_csv(file)
    finally:
        writer.join(5.0)
        os.close(read_end)
    print("loaded from the pipe:", len(path.x), "points")
    assert path_id == 1 and len(path.x) == len(ReferencePath.from_csv(DLC).x)


def _run_cli(args: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "firmware_sim", "--controller", "lmpc",
                           "--lockstep", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def test_broken_dbc_is_an_error_before_the_bus_is_opened(tmp_path):
    """Issue 17, defect 2: a DBC with a syntax error (``BO_ garbage`` appended): the ECU
    started, dropped every frame and never answered the handshake; SIGTERM gave a traceback."""
    dbc = tmp_path / "broken.dbc"
    shutil.copy(REPO / "can_defs" / "vehicle.dbc", dbc)
    with dbc.open("a") as handle:
        handle.write("\nBO_ garbage\n")
    # an interface that cannot open: the DBC must be refused before it is tried
    result = _run_cli(["--interface", "no-such-interface", "--channel", "x",
                       "--path", f"1={DLC}", "--dbc", str(dbc)])
    print("exit", result.returncode, "stderr:", result.stderr)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1
    assert lines[0].startswith("error: cannot load DBC") and "broken.dbc" in lines[0]
    assert "Traceback" not in result.stderr


def test_ecu_close_never_raises_without_a_codec(buses, monkeypatch):
    """Defect 2's shutdown half: with no usable codec, close() still shuts the bus down."""
    import can_defs.codec as codec
    ecu_bus, _ = buses
    ecu = Ecu(ecu_bus, "scripted", {1: Path("x.csv")}, lockstep=True,
              controller_factory=lambda name: ScriptedController(), path_loader=str)
    monkeypatch.setattr(codec, "_CODECS_BY_CLASS", {})
    monkeypatch.setattr(codec, "_CODECS", {})
    monkeypatch.setattr(codec, "load_database",
                        lambda *a: (_ for _ in ()).throw(codec.DbcLoadError("broken")))
    ecu.close()
    assert ecu_bus._is_shutdown  # noqa: SLF001


@pytest.mark.parametrize("case", ["missing-folder", "unwritable-folder", "exists", "is-input"])
def test_timing_out_is_checked_before_the_bus_is_opened(tmp_path, case):
    """Issue 17, defect 3: ``--timing-out`` to a path that cannot be written was not checked;
    at the end a traceback and the timing data lost; a missing folder was created silently."""
    if case == "missing-folder":
        out = tmp_path / "no" / "such" / "timing.npz"
    elif case == "unwritable-folder":
        if os.geteuid() == 0:
            out = Path("/proc/sys/timing.npz")  # root may write almost anywhere else
        else:
            folder = tmp_path / "ro"
            folder.mkdir(mode=0o500)
            out = folder / "timing.npz"
    elif case == "exists":
        out = tmp_path / "timing.npz"
        out.write_bytes(b"earlier run")
    else:
        out = DLC
    result = _run_cli(["--interface", "no-such-interface", "--channel", "x",
                       "--path", f"1={DLC}", "--timing-out", str(out)])
    print(case, "exit", result.returncode, "stderr:", result.stderr)
    assert result.returncode == 2 and result.stderr.startswith("error: --timing-out")
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "no").exists()
    if case == "exists":
        assert out.read_bytes() == b"earlier run"


def test_timing_out_with_replace_overwrites_and_a_late_failure_is_one_error_line(tmp_path, capsys):
    out = tmp_path / "timing.npz"
    out.write_bytes(b"earlier run")
    stop = threading.Event()
    stop.set()
    status = cli.main(["--interface", "virtual", "--channel", f"t-{uuid.uuid4()}",
                       "--controller", "lmpc", "--path", f"1={DLC}", "--lockstep",
                       "--timing-out", str(out), "--replace"], stop_event=stop)
    assert status == 0 and out.read_bytes()[:2] == b"PK"
    # the folder disappears while the ECU runs: one error line at the end, no traceback
    gone = tmp_path / "gone"
    gone.mkdir()
    status = cli.main(["--interface", "virtual", "--channel", f"t-{uuid.uuid4()}",
                       "--controller", "lmpc", "--path", f"1={DLC}", "--lockstep",
                       "--timing-out", str(gone / "t.npz")],
                      stop_event=_StopAfter(lambda: gone.rmdir()))
    err = capsys.readouterr().err
    print("exit", status, "stderr:", err)
    assert status == 1 and "error: --timing-out" in err and "cannot write" in err


class _StopAfter(threading.Event):
    """A stop event that runs ``action`` the first time the ECU loop looks at it, then stops."""

    def __init__(self, action) -> None:
        super().__init__()
        self._action = action

    def is_set(self) -> bool:
        if not super().is_set():
            self._action()
            self.set()
        return True


@pytest.mark.parametrize("content, check", [
    ("x,y,yaw\n0,0,0\n0.25,0,1e300\n0.5,0,0\n", "line 3: yaw"),
    ("x,y,yaw\n" + "".join(f"{0.25 * i},0,3.14159\n" for i in range(10)), "line 2: yaw"),
    ("x,y,yaw\n" + "".join(f"{1e7 + 0.25 * i},0,0\n" for i in range(10)), "line 2: x"),
    ("x,y,yaw\n0,0,0\n0.25,0,0\n0.5,0,3.1\n0.25,0.01,3.1\n", "line 4: the path turns"),
])
def test_nonsense_path_file_latches_fault_with_one_message(buses, caplog, content, check, tmp_path):
    """Issue 17, defect 4: path files that parse but make no sense (yaw 1e300, yaw opposite to
    the points, 10,000 km away, doubling back) were followed with CMD_VALID = 1. Now a load
    failure: FAULT latched, one message naming the file, the line and the check."""
    file = tmp_path / "nonsense.csv"
    file.write_text(content)
    ecu_bus, peer_bus = buses
    with caplog.at_level(logging.ERROR, logger="firmware_sim"):
        ecu = Ecu(ecu_bus, "scripted", {1: file}, lockstep=True,
                  controller_factory=lambda name: ScriptedController())
    rig_peers = PeerNodes(peer_bus)
    rig_peers.send_handshake()
    for t in range(0, 60, 5):
        if t % 10 == 0:
            rig_peers.send_plant(**moving_plant(t))
        if t % 25 == 0:
            rig_peers.send_planner(**engaged(t))
        rig_peers.send_sync(t)
    pump(ecu, ecu_bus)
    sent = rig_peers.received()
    messages = [r.getMessage() for r in caplog.records]
    print(ecu.load_error)
    assert ecu.load_error is not None and "nonsense.csv" in ecu.load_error and check in ecu.load_error
    assert len(messages) == 1 and "FAULT latched" in messages[0]
    assert {c.ctrl_mode for c in commands(sent)} == {CtrlMode.FAULT}
    assert not any(c.cmd_valid for c in commands(sent))
    assert math.isfinite(commands(sent)[-1].steer_angle_cmd)

"""The ECU command line: argument errors, bus errors, signal shutdown (in-process and as a
subprocess), and that importing the ECU never imports torch."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from can_defs.frames import HANDSHAKE_TICK, CtrlMode

from firmware_sim import cli, path_arguments
from firmware_sim.errors import PathArgumentError
from hil.ecu_harness import PeerNodes, commands, decode_messages

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def path_csv(tmp_path: Path) -> Path:
    """A straight 50 m reference path, points 0.5 m apart."""
    file = tmp_path / "straight.csv"
    file.write_text("x,y,yaw\n" + "".join(f"{0.5 * i:.3f},0.0,0.0\n" for i in range(101)))
    return file


# ------------------------------------------------------------------ arguments
@pytest.mark.parametrize("text, message", [
    ("1:file.csv", "expected ID=FILE.csv"), ("1=", "expected ID=FILE.csv"),
    ("one=file.csv", "is not an integer"), ("256=file.csv", "outside 0..255"),
    ("1=/no/such/file.csv", "cannot read")])
def test_bad_path_argument_is_a_typed_error_naming_it(text, message):
    with pytest.raises(PathArgumentError, match=message) as info:
        path_arguments.parse_path_argument(text)
    print(info.value)
    assert repr(text) in str(info.value)


def test_duplicate_path_id_is_refused(path_csv):
    with pytest.raises(PathArgumentError, match="given twice"):
        path_arguments.parse_paths([f"1={path_csv}", f"1={path_csv}"])
    assert path_arguments.parse_paths([f"1={path_csv}", f"7={path_csv}"]) == {1: path_csv, 7: path_csv}


def test_main_prints_error_and_exits_2_for_an_unreadable_path(capsys):
    status = cli.main(["--interface", "virtual", "--channel", "x", "--controller", "lmpc",
                       "--path", "1=/no/such/file.csv", "--lockstep"])
    err = capsys.readouterr().err
    print(status, err)
    assert status == 2 and err.startswith("error: --path") and "Traceback" not in err


def test_unknown_controller_is_a_usage_error(capsys, path_csv):
    with pytest.raises(SystemExit) as info:
        cli.main(["--controller", "pid", "--path", f"1={path_csv}", "--lockstep"])
    err = capsys.readouterr().err
    print(err)
    assert info.value.code == 2
    # one line, no usage text (issue 39 item 7), naming every valid choice
    assert len(err.splitlines()) == 1 and "usage" not in err
    assert err.startswith("error: argument --controller: invalid choice: 'pid'")
    from controller.registry import ALL_CONTROLLER_NAMES
    assert all(f"'{name}'" in err for name in ALL_CONTROLLER_NAMES)


def test_bus_that_cannot_be_opened_exits_1_with_error(capsys, path_csv):
    status = cli.main(["--interface", "no_such_interface", "--channel", "x", "--controller",
                       "lmpc", "--path", f"1={path_csv}", "--realtime"])
    err = capsys.readouterr().err
    print(status, err)
    assert status == 1 and err.startswith("error: cannot open CAN bus") and "Traceback" not in err


def test_controller_choices_are_the_registrys():
    from controller.registry import ALL_CONTROLLER_NAMES
    assert cli.CONTROLLER_CHOICES == ALL_CONTROLLER_NAMES


def test_controller_lists_in_the_docs_are_the_registrys():
    """Issue 39 item 6: every ``--controller {a,b,...}`` in README.md and docs/*.md names
    exactly the registry's controllers, in its order."""
    import re

    from controller.registry import ALL_CONTROLLER_NAMES
    root = Path(__file__).resolve().parents[1]
    found = []
    for doc in [root / "README.md", *sorted((root / "docs").rglob("*.md"))]:
        for choices in re.findall(r"--controller \{([^}]*)\}", doc.read_text()):
            found.append(doc.name)
            assert tuple(choices.split(",")) == ALL_CONTROLLER_NAMES, f"{doc}: {{{choices}}}"
    assert "ecu.md" in found


def test_importing_the_ecu_never_imports_torch():
    code = ("import sys, firmware_sim, firmware_sim.cli, firmware_sim.ecu, hil.ecu_harness, "
            "controller.dead_reckoning; print(sorted(m for m in sys.modules if 'torch' in m))")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    print(result.stdout, result.stderr)
    assert result.returncode == 0 and result.stdout.strip() == "[]"


# ------------------------------------------------------------------ shutdown on a signal
def test_stop_handler_sends_last_invalid_command_and_main_returns_0(path_csv):
    channel = f"ecu-cli-{uuid.uuid4()}"
    stop = threading.Event()
    result: list[int] = []
    with can.Bus(interface="virtual", channel=channel) as peer_bus:
        # main opens its own bus on the same virtual channel, in a thread (signals can only
        # be installed in the main thread, so the handler is called directly below)
        thread = threading.Thread(target=lambda: result.append(cli.main(
            ["--interface", "virtual", "--channel", channel, "--controller", "lmpc",
             "--path", f"1={path_csv}", "--lockstep"], stop_event=stop)))
        thread.start()
        peers = PeerNodes(peer_bus)
        acked = []
        deadline = time.monotonic() + 30.0
        while not acked and time.monotonic() < deadline:
            peers.send_handshake()
            message = peer_bus.recv(0.2)
            if message is not None:
                acked.append(message)
        for t in (0, 5):
            peers.send_plant(vx=5.0)
            peers.send_sync(t)
            time.sleep(0.1)
        cli.make_stop_handler(stop)(signal.SIGTERM, None)
        thread.join(10.0)
        sent = acked + peers.received()
    frames = decode_messages(sent)
    print("frames from the CLI's ECU:", frames)
    assert not thread.is_alive() and result == [0]
    assert frames[0].tick == HANDSHAKE_TICK
    last = commands(sent)[-1]
    assert type(frames[-1]).__name__ == "SteerTorqueCmd"
    assert not last.cmd_valid and last.drive_torque_cmd == 0.0 and last.ctrl_mode is CtrlMode.STANDBY


@pytest.mark.parametrize("signum, via_environment", [(signal.SIGTERM, False),
                                                      (signal.SIGINT, True)])
def test_cli_subprocess_exits_0_quietly_on_signal(path_csv, signum, via_environment):
    args = [sys.executable, "-m", "firmware_sim", "--controller", "lmpc",
            "--path", f"1={path_csv}", "--lockstep", "--log-level", "info"]
    env = dict(os.environ)
    if via_environment:   # --interface / --channel default from python-can's variables
        env.update(CAN_INTERFACE="virtual", CAN_CHANNEL="cli-env")
    else:
        env.pop("CAN_INTERFACE", None)
        env.pop("CAN_CHANNEL", None)
        args[3:3] = ["--interface", "virtual", "--channel", "cli-args"]
    process = subprocess.Popen(args, cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    try:
        ready_line = process.stderr.readline()      # first INFO line: "ready: ..."
        process.send_signal(signum)
        status = process.wait(timeout=20)
        rest = process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        process.stderr.close()
    print("ready line:", ready_line.strip(), "| exit", status, "| rest of stderr:", repr(rest))
    assert "ready: controller lmpc" in ready_line and "mode INIT" in ready_line
    assert status == 0
    assert not any(level in rest for level in ("WARNING", "ERROR", "Traceback"))


# ------------------------------------------------------------------ the process on a loopback bus
class FakeSocketcand:
    """A minimal socketcand server on 127.0.0.1: python-can's ``socketcand`` interface in
    the ECU process connects to it, so the test sees the process's frames (TCP loopback
    only; the protocol is socketcand's ASCII ``< hi >`` / ``< open >`` / ``< rawmode >``)."""

    def __init__(self) -> None:
        import socket
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self._client = None
        self._buffer = ""
        self._reader: threading.Thread | None = None

    def accept(self, timeout_s: float) -> None:
        self._server.settimeout(timeout_s)
        self._client, _ = self._server.accept()
        self._client.settimeout(timeout_s)
        self._client.sendall(b"< hi >")
        assert self._client.recv(256).decode().startswith("< open ")
        self._client.sendall(b"< ok >")
        assert self._client.recv(256) == b"< rawmode >"
        self._client.sendall(b"< ok >")

    def send(self, frame_id: int, data: bytes) -> None:
        self._client.sendall(f"< frame {frame_id:03X} 0.0 {data.hex()} >".encode())

    def start_reading(self) -> None:
        """Collect everything the process sends, in a thread, until it disconnects."""
        def read() -> None:
            try:
                while chunk := self._client.recv(4096):
                    self._buffer += chunk.decode()
            except OSError:   # reset or timeout: the process is gone
                pass
        self._client.settimeout(None)
        self._reader = threading.Thread(target=read)
        self._reader.start()

    def frame_ids(self) -> list[int]:
        """IDs of the frames received so far."""
        return [frame_id for frame_id, _ in self._parse()]

    def frames(self, timeout_s: float) -> list[tuple[int, bytes]]:
        """Frames the process sent until it closed the connection (or ``timeout_s``)."""
        self._reader.join(timeout_s)
        return self._parse()

    def _parse(self) -> list[tuple[int, bytes]]:
        frames = []
        for text in self._buffer.split(">"):
            parts = text.replace("<", " ").split()
            if parts[:1] == ["send"]:
                frames.append((int(parts[1], 16), bytes(int(b, 16) for b in parts[3:])))
        return frames

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        self._server.close()
        if self._reader is not None:
            self._reader.join(5.0)


def test_cli_process_sends_last_invalid_command_on_sigterm(path_csv):
    from can_defs.codec import decode, encode
    from can_defs.frames import FrameId, HilSync

    server = FakeSocketcand()
    env = dict(os.environ, CAN_CONFIG=f'{{"host": "127.0.0.1", "port": {server.port}}}')
    process = subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", "--interface", "socketcand", "--channel", "vcan0",
         "--controller", "lmpc", "--path", f"1={path_csv}", "--lockstep"],
        cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    try:
        server.accept(timeout_s=30.0)
        server.start_reading()
        deadline = time.monotonic() + 30.0
        while FrameId.HIL_SYNC_ACK not in server.frame_ids() and time.monotonic() < deadline:
            server.send(FrameId.HIL_SYNC, encode(HilSync(HANDSHAKE_TICK)))  # every 100 ms
            time.sleep(0.1)
        server.send(FrameId.HIL_SYNC, encode(HilSync(0)))
        while server.frame_ids().count(FrameId.HIL_SYNC_ACK) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        status = process.wait(timeout=20)
        frames = server.frames(timeout_s=2.0)
        stderr = process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        process.stderr.close()
        server.close()
    decoded = [decode(frame_id, data).frame for frame_id, data in frames]
    print("exit", status, "| frames from the process:", decoded, "| stderr:", repr(stderr))
    assert status == 0 and stderr == ""
    # handshakes sent while the ECU was loading may all be answered; then tick 0, then the end
    handshakes = [f for f in decoded if type(f).__name__ == "HilSyncAck" and f.tick == HANDSHAKE_TICK]
    after = decoded[len(handshakes):]
    assert len(handshakes) >= 1 and decoded[:len(handshakes)] == handshakes
    assert [type(f).__name__ for f in after] == ["SteerTorqueCmd", "CtrlDiag", "HilSyncAck",
                                                 "SteerTorqueCmd"]
    assert after[2].tick == 0
    last = decoded[-1]
    assert not last.cmd_valid and last.drive_torque_cmd == 0.0

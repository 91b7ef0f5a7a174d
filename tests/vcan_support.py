"""Shared helpers of the tests that run an ECU on a real SocketCAN ``vcan0``
(tests/test_vcan.py, tests/test_firmware_c_vcan.py, tests/test_vcan_odd_frames.py,
tests/test_vcan_lost_interface.py).

- `vcan_backend`: where vcan0 comes from: the host's, else user-mode Linux (hil/vcan.py),
  else the test skips saying how to enable it (with ``CI=true`` it fails instead).
- `run_with_candump`: a shell command on vcan0 with candump (can-utils) recording the
  ECU's two frames, on the host or inside user-mode Linux.
- `ecu_frames`: the ECU's frames of such a recording, CTRL_DIAG without its wall-clock
  fields; `reference_frames`: the same of the Python ECU on python-can's virtual bus.
- `scenario_copy`: a shipped scenario with an absolute path file (UML's working folder).
- `drive_lockstep` (and this file run as a script): a lockstep rig of hil (``hil.rig``:
  plant, planner, monitor and time master) on vcan0 driving an ECU started by its CLI,
  which the C executable and ``python -m firmware_sim`` share; ``send_hook`` injects
  extra frames.
- `drive_lost_interface` (this file run as a script with ``--lost-interface`` or
  ``--lost-interface-realtime``): the same driver around a lost interface: a lockstep run
  (or the ECU in real time without inputs), vcan0 set down and up again (``ip link``), a
  second run with a new handshake; the ECU's CPU time over the down period
  (`process_cpu_s`) and its log offsets are reported on one `LOST_INTERFACE_REPORT` line.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING

import can
import pytest

from hil.bus import BusConfig
from hil.rig import NoEcu, Rig, RigHooks
from hil.run_types import RunOptions
from hil.time_master import SendHook
from hil.vcan import REPO_ROOT, UML_SAFE_ENV, host_vcan_available, run_in_uml, uml_unavailable_reason

if TYPE_CHECKING:
    from hil.scenario import Scenario

#: The ECU's own frames: STEER_TORQUE_CMD and CTRL_DIAG.
ECU_FRAME_IDS = (0x200, 0x201)
#: The candump filter for exactly those (see tests/test_vcan.py on why it is filtered).
CANDUMP_ECU_FILTER = "200:7FE"


def vcan_backend() -> str:
    """"host" or "uml"; skips the calling test (fails it with ``CI=true``) when neither
    the host nor user-mode Linux can provide vcan0."""
    if host_vcan_available("vcan0"):
        return "host"
    reason = uml_unavailable_reason()
    if reason is None:
        return "uml"
    message = ("no SocketCAN vcan0: this kernel has no CAN (or no vcan0) and user-mode Linux "
               f"is not usable: {reason}")
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(message + " (CI=true: this test must run)")
    pytest.skip(message)


def run_with_candump(run: str, backend: str, candump_log: Path, setup: str = "",
                     candump_options: str = "") -> tuple[int, str, dict]:
    """``run`` (a shell command line) on vcan0 with candump recording the ECU's IDs into
    ``candump_log``, on the host or inside user-mode Linux (``backend``); ``setup`` (a
    shell command line) runs before candump starts (e.g. a change of vcan0's MTU, which
    takes the link down); ``candump_options``: e.g. ``-D`` (stay when vcan0 goes down).

    Returns (exit status, output, the environment the plant's numeric paths need)."""
    command = (f"{setup + ' && ' if setup else ''}"
               f"candump -L {candump_options} vcan0,{CANDUMP_ECU_FILTER} > {candump_log} & CANDUMP=$!; sleep 0.5; "
               f"{run}; status=$?; sleep 0.5; kill $CANDUMP; wait $CANDUMP; exit $status")
    if backend == "uml":
        result = run_in_uml(command, workdir=REPO_ROOT, timeout_s=300)
        print(f"user-mode Linux: {result.wall_s:.1f} s")
        return result.returncode, result.output, UML_SAFE_ENV
    done = subprocess.run(["/bin/sh", "-c", command], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=300)
    return done.returncode, done.stdout + done.stderr, {}


def ecu_frames(log: Path) -> list[tuple[int, bytes]]:
    """The ECU's STEER_TORQUE_CMD and CTRL_DIAG payloads in order; CTRL_DIAG with CRC,
    SOLVE_TIME_US, CYCLE_TIME_US and OVERRUNS zeroed (wall-clock measurements)."""
    frames = []
    for message in can.LogReader(log):
        if message.arbitration_id not in ECU_FRAME_IDS:
            continue
        data = bytearray(message.data)
        if message.arbitration_id == 0x201:
            data[0] = 0                 # CRC covers the timing fields
            data[2:6] = bytes(4)        # SOLVE_TIME_US, CYCLE_TIME_US
            data[7] &= 0xF0             # OVERRUNS (bits 56..59); FAULTS kept
        frames.append((message.arbitration_id, bytes(data)))
    return frames


def scenario_copy(name: str, folder: Path, duration_s: float | None = None) -> Path:
    """The shipped scenario ``name`` written into ``folder`` with an absolute path file
    (the run inside user-mode Linux has another working folder), cut to ``duration_s``."""
    text = (REPO_ROOT / "hil" / "scenarios" / f"{name}.toml").read_text()
    text = text.replace('file = "../paths/dlc.csv"', f'file = "{REPO_ROOT / "hil/paths/dlc.csv"}"')
    assert str(REPO_ROOT) in text, f"{name}.toml no longer names ../paths/dlc.csv"
    if duration_s is not None:
        lines = [f"duration_s = {duration_s}" if line.startswith("duration_s =") else line
                 for line in text.splitlines()]
        text = "\n".join(lines) + "\n"
        assert f"duration_s = {duration_s}" in text
    scenario = folder / f"{name}.toml"
    scenario.write_text(text)
    return scenario


def reference_frames(scenario: Path, controller: str, log: Path, env: dict[str, str]) -> list[tuple[int, bytes]]:
    """`ecu_frames` of the Python ECU on python-can's virtual bus (``hil run --lockstep``),
    with ``env`` (the environment of the vcan0 run, so the plant takes the same numeric
    code paths)."""
    reference = subprocess.run(
        [sys.executable, "-m", "hil", "run", "--scenario", str(scenario), "--controller", controller,
         "--interface", "virtual", "--channel", f"reference-{log.stem}", "--lockstep", "--log", str(log)],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert reference.returncode == 0, reference.stderr[-1500:]
    return ecu_frames(log)


def start_ecu(ecu_program: Sequence[str], controller: str, scenario: Scenario, stderr: IO[bytes] | None = None,
              realtime: bool = False) -> subprocess.Popen:
    """The ECU (``ecu_program`` plus the CLI options both ECUs share) on vcan0 in lockstep
    (``realtime``: on its wall clock) for ``scenario``;
    ``stderr``: where its log goes."""
    return subprocess.Popen([*ecu_program, "--interface", "socketcan", "--channel", "vcan0",
                             "--controller", controller, "--path", f"{scenario.path_id}={scenario.path_file}",
                             "--realtime" if realtime else "--lockstep"], stderr=stderr)


class _StartedEcu(NoEcu):
    """The ECU `start_ecu` started, as the rig's ECU: alive while its process runs;
    `stop_ecu` stops it, not the rig (a second run may follow)."""

    def __init__(self, ecu: subprocess.Popen) -> None:
        self.process = ecu

    def alive_problem(self) -> str | None:
        return None if self.process.poll() is None else "the ECU exited"


def run_lockstep(scenario: Scenario, ecu: subprocess.Popen, send_hook: SendHook | None = None,
                 fd: bool = False) -> None:
    """One lockstep run of ``scenario`` on vcan0 by a new rig (``hil.rig``: its own socket,
    plant and planner nodes): handshake with ``ecu`` (started by `start_ecu`), then ticks
    to the scenario's end. ``send_hook``: `RigHooks.send_hook`; ``fd``: the rig's socket
    may send CAN FD frames."""
    options = RunOptions(controller="(another process)", bus=BusConfig("socketcan", "vcan0"),
                         handshake_timeout_s=120.0, ack_timeout_s=30.0)
    hooks = RigHooks(ecu=lambda rig: _StartedEcu(ecu), send_hook=send_hook, bus_options={"fd": fd})
    with Rig(scenario, options, hooks) as rig:
        rig.run()


def stop_ecu(ecu: subprocess.Popen) -> int:
    """SIGTERM, then the ECU's exit status."""
    ecu.send_signal(signal.SIGTERM)
    status = ecu.wait(timeout=30)
    print("ECU exit status", status)
    return status


def drive_lockstep(scenario_file: str, controller: str, ecu_program: Sequence[str],
                   send_hook: SendHook | None = None, fd: bool = False) -> int:
    """Run the scenario on vcan0: start the ECU (``ecu_program`` plus the CLI options both
    ECUs share), drive it with hil's plant, planner and lockstep time master, stop it with
    SIGTERM. ``send_hook`` sees every tick's node frames (`hil.time_master.SendHook`);
    ``fd``: the master's socket may send CAN FD frames. Returns the ECU's exit status."""
    from hil.scenario import load_scenario

    scenario = load_scenario(scenario_file)
    ecu = start_ecu(ecu_program, controller, scenario)
    try:
        run_lockstep(scenario, ecu, send_hook, fd)
    finally:
        status = stop_ecu(ecu)
    return status


#: Prefix of the one stdout line with `drive_lost_interface`'s measurements (JSON).
LOST_INTERFACE_REPORT = "LOST_INTERFACE_REPORT "


def process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) the process ``pid`` has used (/proc/PID/stat fields 14
    and 15, in clock ticks; the name field may hold spaces, so count after its ')')."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_for_ecu_frame(ecu: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Return once the ECU has sent a frame on vcan0 (it runs its cycles), then 0.5 s more;
    raise if it exits or sends nothing within ``timeout_s``."""
    bus = can.Bus(interface="socketcan", channel="vcan0",
                  can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in ECU_FRAME_IDS])
    try:
        give_up = time.monotonic() + timeout_s
        while bus.recv(timeout=0.5) is None:
            if ecu.poll() is not None or time.monotonic() > give_up:
                raise RuntimeError(f"the ECU sent nothing on vcan0 (exit status {ecu.poll()})")
    finally:
        bus.shutdown()
    time.sleep(0.5)


def drive_lost_interface(scenario_file: str, controller: str, ecu_log: str, ecu_program: Sequence[str],
                         realtime: bool = False, down_s: float = 1.5) -> int:
    """A lost interface under a running ECU, on vcan0 (root needed: ``ip link``).

    Lockstep: the ECU (log to ``ecu_log``) runs the scenario; then vcan0 is set down for
    ``down_s`` and up again, and after 1.2 s (longer than the contract's reopening
    interval) a new time master runs the scenario again from a new handshake (the
    contract: a handshake in the middle of a run restarts the virtual clock). The
    driver's own socket is closed over the down period (its errors are not the subject).
    ``realtime``: the ECU runs on its wall clock without any input (it sends every cycle);
    once its first frame is on vcan0, ``down_s`` with vcan0 up (its CPU time then is the
    baseline), then the same down and 1.2 s up periods, no time master.

    Prints `LOST_INTERFACE_REPORT` + JSON: the ECU's CPU seconds down (and up, in real
    time), whether it was alive after the down period, the wall-clock times (s, the clock of candump's
    timestamps) of down (before and after ``ip link``), up and the end of the 1.2 s after
    it, and the byte offsets of ``ecu_log`` at those times. Returns the ECU's exit status
    on SIGTERM."""
    from hil.scenario import load_scenario

    scenario = load_scenario(scenario_file)
    report: dict[str, float | int | bool] = {"down_s": down_s}
    with open(ecu_log, "wb") as log:
        ecu = start_ecu(ecu_program, controller, scenario, stderr=log, realtime=realtime)
        try:
            if not realtime:
                run_lockstep(scenario, ecu)
            else:
                wait_for_ecu_frame(ecu)  # running, not still starting (seconds in UML under load)
                # the baseline: its CPU time over as long with vcan0 up
                before = process_cpu_s(ecu.pid)
                time.sleep(down_s)
                report["idle_cpu_s"] = process_cpu_s(ecu.pid) - before
            report["down_at"], report["log_at_down"] = time.time(), Path(ecu_log).stat().st_size
            before = process_cpu_s(ecu.pid)
            subprocess.run(["ip", "link", "set", "vcan0", "down"], check=True)
            report["down_done_at"] = time.time()
            time.sleep(down_s)
            report["down_cpu_s"] = process_cpu_s(ecu.pid) - before
            report["up_started_at"] = time.time()
            subprocess.run(["ip", "link", "set", "vcan0", "up"], check=True)
            report["up_at"], report["log_at_up"] = time.time(), Path(ecu_log).stat().st_size
            report["alive_after_down"] = ecu.poll() is None
            time.sleep(1.2)
            report["rerun_at"], report["log_at_rerun"] = time.time(), Path(ecu_log).stat().st_size
            if not realtime:
                run_lockstep(scenario, ecu)  # its own socket, opened after the down period
        finally:
            if ecu.poll() is None:
                report["exit_status"] = stop_ecu(ecu)
            else:
                report["exit_status"] = ecu.returncode
                print("the ECU had exited with status", ecu.returncode)
            print(LOST_INTERFACE_REPORT + json.dumps(report), flush=True)
    return int(report["exit_status"])


if __name__ == "__main__":
    # python tests/vcan_support.py SCENARIO CONTROLLER ECU_PROGRAM...
    # python tests/vcan_support.py --lost-interface[-realtime] ECU_LOG SCENARIO CONTROLLER ECU_PROGRAM...
    if sys.argv[1].startswith("--lost-interface"):
        sys.exit(drive_lost_interface(sys.argv[3], sys.argv[4], sys.argv[2], sys.argv[5:],
                                      realtime=sys.argv[1] == "--lost-interface-realtime"))
    sys.exit(drive_lockstep(sys.argv[1], sys.argv[2], sys.argv[3:]))

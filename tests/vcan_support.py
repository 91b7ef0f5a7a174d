"""Shared helpers of the tests that run an ECU on a real SocketCAN ``vcan0``
(tests/test_vcan.py, tests/test_firmware_c_vcan.py, tests/test_vcan_odd_frames.py).

- `vcan_backend`: where vcan0 comes from: the host's, else user-mode Linux (hil/vcan.py),
  else the test skips saying how to enable it (with ``CI=true`` it fails instead).
- `run_with_candump`: a shell command on vcan0 with candump (can-utils) recording the
  ECU's two frames, on the host or inside user-mode Linux.
- `ecu_frames`: the ECU's frames of such a recording, CTRL_DIAG without its wall-clock
  fields; `reference_frames`: the same of the Python ECU on python-can's virtual bus.
- `scenario_copy`: a shipped scenario with an absolute path file (UML's working folder).
- `drive_lockstep` (and this file run as a script): hil's plant, planner and lockstep time
  master on vcan0 driving an ECU started by its CLI, which the C executable and
  ``python -m firmware_sim`` share; ``send_hook`` injects extra frames.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import can
import pytest

from hil.time_master import SendHook
from hil.vcan import REPO_ROOT, UML_SAFE_ENV, host_vcan_available, run_in_uml, uml_unavailable_reason

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


def run_with_candump(run: str, backend: str, candump_log: Path, setup: str = "") -> tuple[int, str, dict]:
    """``run`` (a shell command line) on vcan0 with candump recording the ECU's IDs into
    ``candump_log``, on the host or inside user-mode Linux (``backend``); ``setup`` (a
    shell command line) runs before candump starts (e.g. a change of vcan0's MTU, which
    takes the link down).

    Returns (exit status, output, the environment the plant's numeric paths need)."""
    command = (f"{setup + ' && ' if setup else ''}"
               f"candump -L vcan0,{CANDUMP_ECU_FILTER} > {candump_log} & CANDUMP=$!; sleep 0.5; "
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


def drive_lockstep(scenario_file: str, controller: str, ecu_program: Sequence[str],
                   send_hook: SendHook | None = None, fd: bool = False) -> int:
    """Run the scenario on vcan0: start the ECU (``ecu_program`` plus the CLI options both
    ECUs share), drive it with hil's plant, planner and lockstep time master, stop it with
    SIGTERM. ``send_hook`` sees every tick's node frames (`hil.time_master.SendHook`);
    ``fd``: the master's socket may send CAN FD frames. Returns the ECU's exit status."""
    from hil.planner_node import PlannerNode
    from hil.plant_node import PlantNode
    from hil.recorder import EcuFrameMonitor
    from hil.scenario import load_scenario
    from hil.time_master import LockstepMaster

    scenario = load_scenario(scenario_file)
    ecu = subprocess.Popen([*ecu_program, "--interface", "socketcan", "--channel", "vcan0",
                            "--controller", controller, "--path", f"{scenario.path_id}={scenario.path_file}",
                            "--lockstep"])
    bus = can.Bus(interface="socketcan", channel="vcan0", fd=fd)
    try:
        master = LockstepMaster(bus, [PlantNode(scenario), PlannerNode(scenario), EcuFrameMonitor()],
                                handshake_timeout_s=120.0, ack_timeout_s=30.0, send_hook=send_hook,
                                peer_alive=lambda: None if ecu.poll() is None else "the ECU exited")
        master.run(scenario.duration_s)
    finally:
        ecu.send_signal(signal.SIGTERM)
        status = ecu.wait(timeout=30)
        bus.shutdown()
    print("ECU exit status", status)
    return status


if __name__ == "__main__":
    # python tests/vcan_support.py SCENARIO CONTROLLER ECU_PROGRAM...
    sys.exit(drive_lockstep(sys.argv[1], sys.argv[2], sys.argv[3:]))

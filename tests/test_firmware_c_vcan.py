"""Equivalence (b) of issue 18: the C ECU executable on a real SocketCAN vcan0 (the host's,
else user-mode Linux, as tests/test_vcan.py), in lockstep with the HIL's plant, planner
and time master as another process, gives the ECU frames of the Python ECU on python-can's
virtual bus: STEER_TORQUE_CMD bit for bit, CTRL_DIAG but its wall-clock fields.

The time master here is a small driver (hil's nodes and LockstepMaster on vcan0), as
``hil run`` would start the Python ECU; candump (can-utils) records the ECU's frames.
``dlc_smoke`` (4 s) here, part of ``make test``; ECU_VCAN_FULL=1 runs the full high-mu
lane change instead (``make firmware-vcan``).
"""
from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from hil.vcan import REPO_ROOT
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)
from test_vcan import _backend, _ecu_frames, run_with_candump

pytestmark = pytest.mark.vcan
CONTROLLER = "lmpc"
ECU = REPO_ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")

#: Plant, planner and lockstep time master on vcan0; the C ECU is another process.
DRIVER = """
import signal, subprocess, sys
import can
from hil.planner_node import PlannerNode
from hil.plant_node import PlantNode
from hil.recorder import EcuFrameMonitor
from hil.scenario import load_scenario
from hil.time_master import LockstepMaster

scenario_file, ecu_path, controller = sys.argv[1:4]
scenario = load_scenario(scenario_file)
ecu = subprocess.Popen([ecu_path, "--interface", "socketcan", "--channel", "vcan0", "--controller", controller,
                        "--path", f"{scenario.path_id}={scenario.path_file}", "--lockstep"])
bus = can.Bus(interface="socketcan", channel="vcan0")
try:
    master = LockstepMaster(bus, [PlantNode(scenario), PlannerNode(scenario), EcuFrameMonitor()],
                            handshake_timeout_s=120.0, ack_timeout_s=30.0,
                            peer_alive=lambda: None if ecu.poll() is None else "C ECU exited")
    master.run(scenario.duration_s)
finally:
    ecu.send_signal(signal.SIGTERM)
    status = ecu.wait(timeout=30)
    bus.shutdown()
print("C ECU exit status", status)
sys.exit(status)
"""


def test_c_ecu_on_vcan0_equals_the_python_ecu_bit_for_bit(native, tmp_path: Path) -> None:
    backend = _backend()
    tmp_path.chmod(0o777)  # written from inside UML as well
    name = "dlc_high_mu" if os.environ.get("ECU_VCAN_FULL") == "1" else "dlc_smoke"
    scenario = tmp_path / f"{name}.toml"  # with an absolute path file (UML's working folder)
    text = (REPO_ROOT / "hil" / "scenarios" / f"{name}.toml").read_text()
    scenario.write_text(text.replace('file = "../paths/dlc.csv"', f'file = "{REPO_ROOT / "hil/paths/dlc.csv"}"'))
    assert str(REPO_ROOT) in scenario.read_text()
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    python = shlex.quote(sys.executable)
    run = f"{python} {driver} {scenario} {ECU} {CONTROLLER}"
    status, output, env = run_with_candump(run, backend, tmp_path / "candump.log")
    assert status == 0, f"the C ECU run on vcan0 failed with status {status}: {output[-1500:]}"
    # The Python ECU on python-can's virtual bus, the plant on the same numeric paths (env).
    reference = subprocess.run(
        [sys.executable, "-m", "hil", "run", "--scenario", str(scenario), "--controller", CONTROLLER,
         "--interface", "virtual", "--channel", "reference-c", "--lockstep", "--log", str(tmp_path / "virtual.log")],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert reference.returncode == 0, reference.stderr[-1500:]
    c_frames = _ecu_frames(tmp_path / "candump.log")
    python_frames = _ecu_frames(tmp_path / "virtual.log")
    print(f"ECU frames: C on vcan0 {len(c_frames)}, Python on the virtual bus {len(python_frames)}")
    assert len(c_frames) >= 2 * 160
    mismatch = next((i for i, (a, b) in enumerate(zip(c_frames, python_frames)) if a != b), None)
    assert mismatch is None, f"frame {mismatch}: C {c_frames[mismatch]} != Python {python_frames[mismatch]}"
    assert len(c_frames) == len(python_frames)

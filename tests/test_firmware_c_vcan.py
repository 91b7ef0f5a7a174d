"""Equivalence (b) of issue 18: the C ECU executable on a real SocketCAN vcan0 (the host's,
else user-mode Linux, as tests/test_vcan.py), in lockstep with the HIL's plant, planner
and time master as another process, gives the ECU frames of the Python ECU on python-can's
virtual bus: STEER_TORQUE_CMD bit for bit, CTRL_DIAG but its wall-clock fields.

The time master here is the shared driver of tests/vcan_support.py (hil's nodes and
LockstepMaster on vcan0), which starts the ECU by its CLI as ``hil run`` starts the Python
ECU; candump (can-utils) records the ECU's frames. ``dlc_smoke`` (4 s) here, part of
``make test``; ECU_VCAN_FULL=1 runs the full high-mu lane change instead (``make
firmware-vcan``).
"""
from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

import pytest

from hil.vcan import REPO_ROOT
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)
from vcan_support import ecu_frames, reference_frames, run_with_candump, scenario_copy, vcan_backend

pytestmark = pytest.mark.vcan
CONTROLLER = "lmpc"
ECU = REPO_ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")


def test_c_ecu_on_vcan0_equals_the_python_ecu_bit_for_bit(native, tmp_path: Path) -> None:
    backend = vcan_backend()
    tmp_path.chmod(0o777)  # written from inside UML as well
    name = "dlc_high_mu" if os.environ.get("ECU_VCAN_FULL") == "1" else "dlc_smoke"
    scenario = scenario_copy(name, tmp_path)  # with an absolute path file (UML's working folder)
    # Plant, planner and lockstep time master on vcan0 (tests/vcan_support.py run as a
    # script); the C ECU is another process, started by it through its CLI.
    run = shlex.join([sys.executable, str(REPO_ROOT / "tests" / "vcan_support.py"), str(scenario), CONTROLLER,
                      str(ECU)])
    status, output, env = run_with_candump(run, backend, tmp_path / "candump.log")
    assert status == 0, f"the C ECU run on vcan0 failed with status {status}: {output[-1500:]}"
    # The Python ECU on python-can's virtual bus, the plant on the same numeric paths (env).
    python_frames = reference_frames(scenario, CONTROLLER, tmp_path / "virtual.log", env)
    c_frames = ecu_frames(tmp_path / "candump.log")
    print(f"ECU frames: C on vcan0 {len(c_frames)}, Python on the virtual bus {len(python_frames)}")
    assert len(c_frames) >= 2 * 160
    mismatch = next((i for i, (a, b) in enumerate(zip(c_frames, python_frames)) if a != b), None)
    assert mismatch is None, f"frame {mismatch}: C {c_frames[mismatch]} != Python {python_frames[mismatch]}"
    assert len(c_frames) == len(python_frames)

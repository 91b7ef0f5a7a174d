"""CAN FD, remote, error and wrong-length frames on the ECU's receive IDs, on a real
SocketCAN vcan0 (the host's, else user-mode Linux, as tests/test_vcan.py): the C ECU
executable and the Python ECU (``python -m firmware_sim``), each as its own process,
driven in lockstep through the contract's normal start by hil's plant, planner and time
master (tests/vcan_support.py) while tests/vcan_odd_frames.py adds, window by window,
CAN FD frames (also with bit-rate switch) carrying the next frame with a valid CRC,
remote frames, error frames, and classic frames of 0..7 bytes, on every receive ID
(HIL_SYNC look-alikes carry the handshake TICK); candump records the ECU's frames.

What the contract (rev. 2, "Receiving rules") says, and what is asserted:

- FD, remote and error frames are never contract frames: ignored before any other rule,
  never a FAULTS bit. So the ECU's frames equal those of the Python ECU on python-can's
  virtual bus without any odd frame: STEER_TORQUE_CMD bit for bit (ACTIVE, CMD_VALID = 1,
  within the limits, alive counter +1 per cycle), CTRL_DIAG but its wall-clock fields.
- A contract frame whose length is not 8 is discarded and counted as an E2E error: the
  same frames, except FAULTS bit 1 in exactly the CTRL_DIAG of the cycles that follow
  such a frame (the ECU stays ACTIVE: the real frames keep coming).

vcan0 carries all of them: a probe socket on the bus that asks for FD and error frames
(CAN_RAW_FD_FRAMES, CAN_RAW_ERR_FILTER) counts every odd frame sent (vcan echoes error
frames written by a process like any other frame; CAN FD needs vcan0's MTU at 72, which
the test sets inside user-mode Linux). How each ECU ignores them differs: the C ECU's
raw socket enables neither option, so the kernel never hands it FD or error frames, and
it drops remote frames by their flag (firmware/src/os_linux.c); python-can's socket
enables error frames (not FD), and the Python ECU drops them by their flags
(firmware_sim/ecu.py ``is_contract_data_frame``).

About 1.5 s of virtual time per ECU (``dlc_smoke`` cut short, LMPC); run time and the
command: docs/vcan.md.
"""
from __future__ import annotations

import json
import math
import os
import shlex
import sys
from pathlib import Path

import pytest

from can_defs.codec import decode
from can_defs.frames import TICK_STEP_MS, CtrlMode, FrameId
from firmware_sim.config import EcuConfig
from hil.vcan import UML_SAFE_ENV
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)
from vcan_odd_frames import KINDS, REPORT_PREFIX, WINDOWS, window_kind
from vcan_support import (REPO_ROOT, ecu_frames, reference_frames, run_with_candump, scenario_copy,
                          vcan_backend)

pytestmark = pytest.mark.vcan

CONTROLLER = "lmpc"
DURATION_S = 1.5
CONTROL_PERIOD_MS = EcuConfig().control_period_ms
#: FAULTS bit 1 (E2E error) as CTRL_DIAG.FAULTS holds it.
E2E_ERROR_BIT = 0b0010
#: A CAN FD frame needs this MTU on vcan0 (CANFD_MTU; the default is 16, CAN_MTU).
CANFD_MTU = 72
SET_FD_MTU = f"ip link set vcan0 down && ip link set vcan0 mtu {CANFD_MTU} && ip link set vcan0 up"
#: The C executable (ECU_EXE: another build, e.g. make firmware-asan's) and the Python ECU.
ECU_PROGRAMS = {"c": [str(REPO_ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu"))],
                "python": [sys.executable, "-m", "firmware_sim"]}


def kinds_before(cycle_ms: int) -> set[str]:
    """The odd frame kinds sent since the previous control cycle, as the cycle at
    ``cycle_ms`` sees them (the frames of tick t come before HIL_SYNC t, so the cycle at t
    has those of the ticks after the previous cycle up to t)."""
    ticks = range(cycle_ms - CONTROL_PERIOD_MS + TICK_STEP_MS, cycle_ms + TICK_STEP_MS, TICK_STEP_MS)
    return {kind for tick in ticks if (kind := window_kind(tick)) is not None}


def without_e2e_bit(data: bytes) -> bytes:
    """A CTRL_DIAG payload (CRC already zeroed) with FAULTS bit 1 cleared (bit 61)."""
    return data[:7] + bytes([data[7] & ~(E2E_ERROR_BIT << 4)])


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(scenario file, the Python ECU's frames on the virtual bus without odd frames,
    backend): one reference for both ECUs."""
    backend = vcan_backend()
    folder = tmp_path_factory.mktemp("odd-frames")
    folder.chmod(0o777)  # written from inside UML as well
    scenario = scenario_copy("dlc_smoke", folder, DURATION_S)
    env = {} if backend == "host" else UML_SAFE_ENV
    return scenario, reference_frames(scenario, CONTROLLER, folder / "reference.log", env), backend


@pytest.mark.parametrize("ecu", ["c", "python"])
def test_ecu_ignores_fd_remote_and_error_frames_and_counts_wrong_lengths(ecu: str, reference, request,
                                                                          tmp_path: Path) -> None:
    scenario, expected, backend = reference
    if ecu == "c":
        request.getfixturevalue("native")  # make firmware
    setup = ""
    if backend == "uml":
        setup = SET_FD_MTU
    elif int(Path("/sys/class/net/vcan0/mtu").read_text()) != CANFD_MTU:
        pytest.skip(f"the host's vcan0 carries no CAN FD: sudo ip link set vcan0 mtu {CANFD_MTU}")
    tmp_path.chmod(0o777)
    driver = REPO_ROOT / "tests" / "vcan_odd_frames.py"
    run = shlex.join([sys.executable, str(driver), str(scenario), CONTROLLER, *ECU_PROGRAMS[ecu]])
    status, output, _ = run_with_candump(run, backend, tmp_path / "candump.log", setup=setup)
    assert status == 0, f"the {ecu} ECU's run on vcan0 failed with status {status}: {output[-2000:]}"

    # Every odd frame was on vcan0: the probe received each one sent.
    report = json.loads(next(line for line in output.splitlines() if line.startswith(REPORT_PREFIX))
                        [len(REPORT_PREFIX):])
    print(f"{ecu} ECU, odd frames sent / received by the probe: {report}")
    for kind in KINDS:
        assert report["sent"].get(kind, 0) > 0, f"no {kind} frame injected"
        assert report["seen"].get(kind, 0) == report["sent"][kind], f"vcan0 did not carry every {kind} frame"

    frames = ecu_frames(tmp_path / "candump.log")
    cycles = round(DURATION_S * 1000 / CONTROL_PERIOD_MS)
    commands = [data for fid, data in frames if fid == FrameId.STEER_TORQUE_CMD]
    diags = [data for fid, data in frames if fid == FrameId.CTRL_DIAG]
    assert len(diags) == cycles and len(commands) == cycles + 1  # + the CMD_VALID = 0 on close
    config = EcuConfig()
    first_counter = commands[0][1] & 0x0F
    for cycle, data in enumerate(commands[1:cycles], start=1):  # ACTIVE from the second cycle
        tick = cycle * CONTROL_PERIOD_MS
        command = decode(FrameId.STEER_TORQUE_CMD, data)
        frame = command.frame
        where = f"cycle at {tick} ms (odd frames since the last cycle: {', '.join(kinds_before(tick)) or 'none'})"
        assert frame.ctrl_mode == CtrlMode.ACTIVE and frame.cmd_valid, f"{where}: {frame}"
        assert math.isfinite(frame.steer_angle_cmd) and abs(frame.steer_angle_cmd) <= config.steer_limit_rad, where
        assert abs(frame.drive_torque_cmd) <= config.drive_torque_limit_nm, where
        # the stream continues: one command per cycle, alive counter +1, CRC valid
        assert command.crc_ok and command.counter == (first_counter + cycle) % 16, f"{where}: {command}"

    # FAULTS bit 1 (E2E error) in exactly the cycles with a wrong-length frame before them
    faults = {cycle * CONTROL_PERIOD_MS: decode(FrameId.CTRL_DIAG, data).frame.faults
              for cycle, data in enumerate(diags)}
    flagged = {tick for tick in faults if "wrong_dlc" in kinds_before(tick)}
    wrong = {t: f for t, f in faults.items() if bool(f & E2E_ERROR_BIT) != (t in flagged)}
    print(f"{ecu} ECU: FAULTS bit 1 in cycles {sorted(t for t, f in faults.items() if f & E2E_ERROR_BIT)} ms "
          f"(expected {sorted(flagged)})")
    assert not wrong, f"FAULTS bit 1 wrong at cycle (ms): FAULTS {wrong}"

    # Nothing else changed: the frames of the run without odd frames, FAULTS bit 1 aside.
    ours = [(fid, without_e2e_bit(d) if fid == FrameId.CTRL_DIAG else d) for fid, d in frames]
    theirs = [(fid, without_e2e_bit(d) if fid == FrameId.CTRL_DIAG else d) for fid, d in expected]
    mismatch = next((i for i, (a, b) in enumerate(zip(ours, theirs)) if a != b), None)
    assert mismatch is None, f"ECU frame {mismatch}: vcan0 with odd frames {ours[mismatch]}, " \
                             f"virtual bus without {theirs[mismatch]}"
    assert len(ours) == len(theirs)

"""The C ECU executable on a bus, lockstep: equivalence with the Python ECU.

The executable runs as its own process on the socketcand hub of the timing tests
(``hil.timing.hub``, TCP loopback); this process runs the plant, the planner and the time
master of ``hil`` on the same hub. Its frames are compared with those of the Python ECU
(in-process, virtual bus) on the same scenario: STEER_TORQUE_CMD byte for byte, CTRL_DIAG
in every field but the wall-clock ones (SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS: the
contract says those are the only fields not repeatable) and the CRC that covers them.
``dlc_smoke`` here (``make test``); both full lane changes with ECU_EQUIVALENCE_FULL=1.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import can
import pytest

from can_defs.codec import decode
from can_defs.frames import FrameId
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)

ROOT = Path(__file__).resolve().parent.parent
ECU = ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")
CHANNEL = "vcan0"
FULL = os.environ.get("ECU_EQUIVALENCE_FULL") == "1"


def run_c_ecu(scenario_name: str, controller: str, log: Path, path_file: Path | None = None):
    """The scenario with the C ECU on the hub (``path_file`` in place of the scenario's):
    (the monitor's raw frames, tracking, exit status, the ECU's output)."""
    from hil.planner_node import PlannerNode
    from hil.plant_node import PlantNode
    from hil.recorder import EcuFrameMonitor
    from hil.scenario import load_scenario
    from hil.session import control_instant_metrics, reference_path
    from hil.time_master import LockstepMaster
    from hil.timing.hub import LoopbackCanHub

    scenario = load_scenario(scenario_name)
    hub = LoopbackCanHub(port=0).start()
    with log.open("w") as output:
        ecu = subprocess.Popen([str(ECU), "--interface", "socketcand", "--channel", CHANNEL, "--port", str(hub.port),
                                "--controller", controller, "--path", f"{scenario.path_id}={path_file or scenario.path_file}",
                                "--lockstep"], cwd=ROOT, stdout=output, stderr=subprocess.STDOUT)
        bus = None
        try:
            bus = can.Bus(interface="socketcand", channel=CHANNEL, host="127.0.0.1", port=hub.port, tcp_tune=True)
            time.sleep(0.2)  # the hub delivers to a new client after its READY_DELAY_S
            plant, planner, monitor = PlantNode(scenario), PlannerNode(scenario), EcuFrameMonitor()
            master = LockstepMaster(bus, [plant, planner, monitor], handshake_timeout_s=30.0, ack_timeout_s=10.0,
                                    peer_alive=lambda: None if ecu.poll() is None else f"ECU exited {ecu.returncode}")
            master.run(scenario.duration_s)
            time.sleep(0.1)
        finally:
            ecu.send_signal(signal.SIGTERM)
            status = ecu.wait(timeout=10)
            if bus is not None:
                bus.shutdown()
            hub.close()
    tracking = control_instant_metrics(plant.trace(), reference_path(scenario))
    return monitor.raw, tracking, status, log.read_text()


def diag_fields(data: bytes) -> tuple:
    """CTRL_DIAG without its wall-clock fields (SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS)."""
    frame = decode(FrameId.CTRL_DIAG, data).frame
    return data[1] & 0x0F, int(frame.qp_status), frame.qp_iter, frame.faults


def check_equivalent(scenario_name: str, controller: str, tmp_path: Path) -> dict:
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    python_run = run_hil(load_scenario(scenario_name), default_options(controller))
    c_raw, c_tracking, status, output = run_c_ecu(scenario_name, controller, tmp_path / "ecu.log")
    assert status == 0, output
    python_raw = python_run.extra["ecu_frames_raw"]
    commands = lambda raw: [(t, d) for t, i, d in raw if i == FrameId.STEER_TORQUE_CMD]  # noqa: E731
    diags = lambda raw: [(t, diag_fields(d)) for t, i, d in raw if i == FrameId.CTRL_DIAG]  # noqa: E731
    ours, theirs = commands(python_raw), commands(c_raw)
    differing = sum(a != b for a, b in zip(ours, theirs))
    figures = {"commands": len(ours), "c_commands": len(theirs), "differing": differing,
               "rmse_python": python_run.tracking.lateral.rmse, "rmse_c": c_tracking.lateral.rmse}
    print(f"{controller} on {scenario_name}: {figures}")
    assert len(theirs) == len(ours) and differing == 0
    assert diags(c_raw) == diags(python_raw)
    return figures


@pytest.mark.parametrize("controller", ["eso-dkmpc", "lmpc"])
def test_c_ecu_on_the_bus_equals_python_ecu_on_dlc_smoke(native, controller: str, tmp_path: Path) -> None:
    check_equivalent("dlc_smoke", controller, tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(not FULL, reason="the full lane changes: make firmware-equivalence (ECU_EQUIVALENCE_FULL=1)")
@pytest.mark.parametrize("scenario", ["dlc_high_mu", "dlc_low_mu"])
@pytest.mark.parametrize("controller", ["eso-dkmpc", "dkmpc", "lmpc"])
def test_c_ecu_on_the_bus_equals_python_ecu_on_full_lane_changes(native, controller: str, scenario: str,
                                                                 tmp_path: Path) -> None:
    check_equivalent(scenario, controller, tmp_path)


def test_a_path_that_does_not_load_latches_fault(native, tmp_path: Path) -> None:
    """As the Python ECU (contract): the handshake is answered, every command is FAULT
    with CMD_VALID = 0, and the reason is on stderr."""
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,heading\n0,0,0\n0.1,0,0\n")
    raw, _, status, output = run_c_ecu("dlc_smoke", "lmpc", tmp_path / "ecu.log", path_file=bad)
    assert status == 0
    assert "FAULT latched: PATH_ID 1 file" in output and "header must be 'x,y,yaw'" in output
    commands = [decode(i, d).frame for _, i, d in raw if i == FrameId.STEER_TORQUE_CMD]
    assert len(commands) == 160
    assert all(int(c.ctrl_mode) == 5 and not c.cmd_valid and c.drive_torque_cmd == 0.0 for c in commands)

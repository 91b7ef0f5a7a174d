"""A lost SocketCAN interface under a running ECU: vcan0 set down and up again (``ip
link``) on a real vcan0 (the host's only as root, else user-mode Linux, as
tests/test_vcan.py), for the C ECU executable and the Python ECU (``python -m
firmware_sim``), each its own process, in lockstep (driven by hil's plant, planner and time
master) and in real time (no inputs); tests/vcan_support.py `drive_lost_interface`;
candump (``-D``: it would end itself when vcan0 goes down) records the ECU's frames.

What the kernel does (user-mode Linux 6.1, docs/vcan.md "A lost vcan0"): a raw CAN socket
bound to vcan0 gets one ENETDOWN when the interface goes down, taken by its next read or
send, whichever comes first; then reads wait as on a silent bus and sends fail with
ENETDOWN while it is down; after ``ip link set vcan0 up`` the same socket receives and
sends again without being reopened (only the interface's removal unbinds it).

So under the contract (rev. 2, "A lost bus": receive errors that persist for 100 ms, or
the end of the stream) a down period is one failed read at most, not a lost bus. Asserted,
for both ECUs in both modes:

- the process neither exits nor crashes (alive after the down period, exit status 0 on
  SIGTERM at the end);
- no lost bus and no reopening in its log; the failed read logged at most once (exactly
  once in lockstep, where the ECU waits in a read); no line per read or per send: each
  kind of line at most once a second;
- no busy loop: its CPU time over the 1.5 s down period below 0.75 s (a busy loop uses
  all 1.5 s; in real time printed beside its CPU time over 1.5 s with vcan0 up);
- no frame of it on vcan0 while down;
- afterwards it works on the same socket. Lockstep: it answers a new handshake and runs
  the scenario again, ACTIVE with CMD_VALID = 1 from the second cycle, every command
  within the limits with a valid CRC and the alive counter +1 per cycle, one CTRL_DIAG
  per cycle. Real time: it sends again at once, a command (CMD_VALID = 0, no inputs) in
  at least 80 % of the cycles after up, CRC valid, the alive counter +1 per frame.

About 0.5 s of virtual time per lockstep run, two runs (``dlc_smoke`` cut short, LMPC);
run time and figures: docs/vcan.md.
"""
from __future__ import annotations

import json
import math
import os
import re
import shlex
import sys
from pathlib import Path

import can
import pytest

from can_defs.codec import decode
from can_defs.frames import CtrlMode, FrameId
from firmware_sim.config import EcuConfig
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)
from test_vcan_odd_frames import ECU_PROGRAMS  # the C executable (ECU_EXE) and the Python ECU
from vcan_support import LOST_INTERFACE_REPORT, REPO_ROOT, run_with_candump, scenario_copy, vcan_backend

pytestmark = pytest.mark.vcan

CONTROLLER = "lmpc"
DURATION_S = 0.5
DOWN_S = 1.5
#: The most CPU time (s) an ECU may use over the DOWN_S down period: half of it; a busy
#: loop uses all of it. (UML's accounting is sampled per tick and noisy on a loaded host:
#: in real time the C ECU measured 0.00 to 0.26 s down, the Python ECU 0.01 to 0.31 s.)
MAX_DOWN_CPU_S = 0.75
#: Frames timestamped this long (s) after ``ip link set vcan0 down`` returned count as sent
#: while down (one cycle sent just before it took effect was seen up to 10 ms after).
DOWN_MARGIN_S = 0.1
CONTROL_PERIOD_MS = EcuConfig().control_period_ms


def bus_lines(log: str) -> list[str]:
    """The lines of an ECU log about its bus: failed receives and sends, a lost or
    reopened bus."""
    return [line for line in log.splitlines() if any(word in line.lower() for word in ("bus", "send", "transmit"))]


def check_run(commands: list[bytes], diags: list[bytes], where: str) -> None:
    """One lockstep run from its handshake: one CTRL_DIAG per control cycle, one
    STEER_TORQUE_CMD per cycle, ACTIVE with CMD_VALID = 1 from the second cycle, within the
    limits, CRC valid, alive counter +1 per cycle."""
    cycles = round(DURATION_S * 1000 / CONTROL_PERIOD_MS)
    assert len(diags) == cycles and len(commands) >= cycles, \
        f"{where}: {len(diags)} CTRL_DIAG, {len(commands)} STEER_TORQUE_CMD for {cycles} cycles"
    config = EcuConfig()
    first_counter = decode(FrameId.STEER_TORQUE_CMD, commands[0]).counter
    for cycle, data in enumerate(commands[:cycles]):
        command = decode(FrameId.STEER_TORQUE_CMD, data)
        frame = command.frame
        at = f"{where}, cycle {cycle}"
        assert command.crc_ok and command.counter == (first_counter + cycle) % 16, f"{at}: {command}"
        assert math.isfinite(frame.steer_angle_cmd) and abs(frame.steer_angle_cmd) <= config.steer_limit_rad, at
        assert abs(frame.drive_torque_cmd) <= config.drive_torque_limit_nm, at
        if cycle >= 1:
            assert frame.ctrl_mode == CtrlMode.ACTIVE and frame.cmd_valid, f"{at}: {frame}"


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> tuple[Path, str]:
    """(the scenario file, the backend); root is needed for ``ip link`` on a host vcan0."""
    backend = vcan_backend()
    if backend == "host" and os.geteuid() != 0:
        pytest.skip("setting the host's vcan0 down and up needs root (ip link set vcan0 down)")
    folder = tmp_path_factory.mktemp("lost-interface")
    folder.chmod(0o777)  # written from inside UML as well
    return scenario_copy("dlc_smoke", folder, DURATION_S), backend


def read_report(output: str) -> dict:
    """The driver's `LOST_INTERFACE_REPORT` line as a dict."""
    line = next(line for line in output.splitlines() if line.startswith(LOST_INTERFACE_REPORT))
    return json.loads(line[len(LOST_INTERFACE_REPORT):])


def frames_by_phase(candump_log: Path, report: dict) -> dict[str, dict[int, list[bytes]]]:
    """The ECU's payloads by ID in the phases "before" (vcan0 up), "down" (from
    DOWN_MARGIN_S after ``ip link set vcan0 down`` returned to up), "up" (the 1.2 s after
    up) and "after"; frames within the margin, or while ``ip link set vcan0 up`` runs, are in none."""
    phases: dict[str, dict[int, list[bytes]]] = {
        name: {FrameId.STEER_TORQUE_CMD: [], FrameId.CTRL_DIAG: []} for name in ("before", "down", "up", "after")}
    for message in can.LogReader(candump_log):
        if message.arbitration_id not in (FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG):
            continue
        t = message.timestamp
        if report["down_done_at"] <= t < report["down_done_at"] + DOWN_MARGIN_S:
            continue
        # vcan0 is up somewhere inside `ip link set vcan0 up`: a frame then is in no phase.
        if report["up_started_at"] <= t < report["up_at"]:
            continue
        phase = ("before" if t < report["down_done_at"] else "down" if t < report["up_at"]
                 else "up" if t < report["rerun_at"] else "after")
        phases[phase][message.arbitration_id].append(bytes(message.data))
    return phases


def log_kinds(lines: list[str]) -> dict[str, int]:
    """Lines per kind of message: without the Python logger's time stamp and the rate
    limiter's "(N more like this ...)" suffix."""
    kinds: dict[str, int] = {}
    for line in lines:
        kind = re.sub(r"^\d{4}-\d\d-\d\d [\d:,]+ ", "", line)
        kind = re.sub(r" \(\d+ more like this.*\)$", "", kind)
        kinds[kind] = kinds.get(kind, 0) + 1
    return kinds


@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
@pytest.mark.parametrize("ecu", ["c", "python"])
def test_ecu_survives_vcan0_down_and_up(ecu: str, mode: str, scenario, request, tmp_path: Path) -> None:
    scenario_file, backend = scenario
    if ecu == "c":
        request.getfixturevalue("native")  # make firmware
    tmp_path.chmod(0o777)
    ecu_log = tmp_path / "ecu.log"
    option = "--lost-interface" if mode == "lockstep" else "--lost-interface-realtime"
    run = shlex.join([sys.executable, str(REPO_ROOT / "tests" / "vcan_support.py"), option,
                      str(ecu_log), str(scenario_file), CONTROLLER, *ECU_PROGRAMS[ecu]])
    # candump -D: candump itself would end when vcan0 goes down
    status, output, _ = run_with_candump(run, backend, tmp_path / "candump.log", candump_options="-D")
    log = ecu_log.read_text(errors="replace") if ecu_log.exists() else ""
    assert LOST_INTERFACE_REPORT in output, f"the driver reported nothing: {output[-2000:]}\nECU log: {log[-1500:]}"
    report = read_report(output)
    where = f"{ecu} ECU, {mode}"
    print(f"{where}: {report}")
    print(f"{where}, log:\n{log}")
    assert status == 0 and report["exit_status"] == 0, \
        f"{where}: the run failed with status {status}: {output[-2000:]}\nECU log: {log[-1500:]}"
    assert report["alive_after_down"], f"{where}: the ECU exited while vcan0 was down"

    # One socket error (ENETDOWN), no lost bus, so nothing to reopen; no line once per
    # read or send. Lockstep: the ECU waits in a read, which takes the error: logged once.
    # Real time: its next read or send takes it, whichever comes first (a send in the C ECU
    # is not logged); failed sends at most once a second per kind of line.
    during = bus_lines(log.encode()[report["log_at_down"]:report["log_at_rerun"]].decode(errors="replace"))
    kinds = log_kinds(during)
    print(f"{where}, bus log lines while down and 1.2 s after: {kinds}")
    receive_failed = sum("receive failed" in line for line in during)
    assert receive_failed == 1 if mode == "lockstep" else receive_failed <= 1, f"{where}: {during}"
    window_s = report["rerun_at"] - report["down_at"]
    assert all(count <= math.ceil(window_s) + 1 for count in kinds.values()), f"{where}: {kinds}"
    assert not any("lost" in line and "persists" not in line for line in bus_lines(log)), f"{where}: {log}"
    assert not any("reopen" in line for line in bus_lines(log)), f"{where}: {log}"

    # No busy loop while the interface was down: a busy loop uses all of DOWN_S (a shell
    # loop in the ECU's place measured 1.53 s).
    assert report["down_cpu_s"] < MAX_DOWN_CPU_S, \
        f"{where}: {report['down_cpu_s']:.2f} s of CPU over {DOWN_S} s with vcan0 down " \
        f"(up: {report.get('idle_cpu_s', 'not measured')} s)"

    phases = frames_by_phase(tmp_path / "candump.log", report)
    assert not any(phases["down"].values()), f"{where}: sent while vcan0 was down: {phases['down']}"
    if mode == "lockstep":
        # Both runs complete and valid on the same socket; nothing between them (no tick).
        assert not any(phases["up"].values()), f"{where}: sent without a tick: {phases['up']}"
        for name in ("before", "after"):
            check_run(phases[name][FrameId.STEER_TORQUE_CMD], phases[name][FrameId.CTRL_DIAG],
                      f"{where}, the run {name} vcan0 was down")
    else:
        # Without inputs: CMD_VALID = 0 every cycle; sending resumes on the same socket
        # at once, the alive counter +1 per cycle sent (the cycles while down are lost).
        commands = phases["up"][FrameId.STEER_TORQUE_CMD]
        expected = (report["rerun_at"] - report["up_at"]) * 1000 / CONTROL_PERIOD_MS
        print(f"{where}: {len(commands)} commands in the {expected:.0f} cycles after up")
        assert len(commands) >= 0.8 * expected, f"{where}: {len(commands)} commands after up"
        decoded = [decode(FrameId.STEER_TORQUE_CMD, data) for data in commands]
        for k, command in enumerate(decoded):
            assert command.crc_ok and not command.frame.cmd_valid, f"{where}: {command}"
            assert command.counter == (decoded[0].counter + k) % 16, f"{where}: command {k} after up"

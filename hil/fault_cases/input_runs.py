"""The input-file cases' runs (`run_input_case`): the ECU, Python or C, as a process on a
socketcand hub of the run's own (the rig of ``hil.session.run_hil``: ``hil.rig.Rig``), started
with the case's bad file (``hil.fault_cases.input_cases``), and judged by the verdict the
case expects:

- a refusal (`_judge_refusal`): only the start-up handshake is tried; the ECU must exit with
  status 2 having printed one ``error:`` line, and a listener on the hub must see no frame
  from it. An ECU that answers the handshake has started: not refused;
- a latched FAULT (`_fault_rows`): the whole scenario, judged by ``evaluate`` as every run
  is, plus rows of its own: FAULT at every control task, CMD_VALID = 0 in every command, a
  ``FAULT latched`` line naming what the case says;
- a failing controller (`_safe_stop_rows`): the whole scenario, judged by ``evaluate``, plus
  rows of its own: SAFE_STOP within `CONTROLLER_FAILED_BOUND_MS` of the first fallback,
  held to the end with CMD_VALID = 1, and the safe stop's command (steering towards
  straight at the bounded rate, no drive torque).

Both ECUs run as processes, so that the Python ECU's exit status is its command line's, as
the C ECU's is.
"""
from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from can_defs.frames import CtrlMode, FrameId
from hil.fault_cases.catalogue import CONTROLLER_FAILED_BOUND_MS, SCENARIO, FaultCase
from hil.fault_cases.input_cases import BadInput, write_bad_input
from hil.fault_cases.verdicts import Verdict, evaluate

#: Exit status of an ECU refusing its arguments or input files (both command lines).
EXIT_USAGE = 2
#: Frames only an ECU sends.
ECU_FRAME_IDS = frozenset({FrameId.HIL_SYNC_ACK, FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG})
#: Wall clock an ECU process may take to start (a loaded machine, the Python ECU's imports).
START_TIMEOUT_S = 60.0
#: The safe stop's steering step per control task (contract: towards straight at a bounded
#: rate; the ECU's 0.2 rad/s over 25 ms) plus one LSB of STEER_ANGLE_CMD.
SAFE_STOP_STEER_STEP_RAD = 0.2 * 0.025 + 1e-4


def _ecu_command(rig: Any, ecu: str, bad: BadInput) -> tuple[list[str], dict[str, str]]:
    """Command line and environment of ``ecu`` ("python", "c") on the rig's hub, given
    ``bad`` (its path file, model / data file, excitation program)."""
    from hil.bus import BusConfig
    from hil.ecu_runners import c_ecu_command, ecu_command
    from hil.run_types import HUB_CHANNEL
    from hil.timing.hub import LOOPBACK

    scenario, options = rig.scenario, rig.options
    if bad.path_file is not None:   # for the ECU only: the rig's planner and metrics keep theirs
        scenario = dataclasses.replace(scenario, path_file=bad.path_file)
    if ecu == "c":
        command = c_ecu_command(scenario, options, rig.hub_port)
        if bad.data is not None:
            command[command.index("--data") + 1] = str(bad.data)
        return command, dict(os.environ)
    options = dataclasses.replace(options, bus=BusConfig("socketcand", HUB_CHANNEL))
    # python-can reads the hub's address from CAN_CONFIG
    environment = dict(os.environ, CAN_CONFIG=json.dumps({"host": LOOPBACK, "port": rig.hub_port,
                                                          "tcp_tune": True}))
    return ecu_command(scenario, options), environment


def _drain(listener: can.BusABC) -> int:
    """Frames of an ECU among those ``listener`` heard (read until it is quiet)."""
    count = 0
    while (message := listener.recv(timeout=0.3)) is not None:
        count += message.arbitration_id in ECU_FRAME_IDS
    return count


def _run(case: FaultCase, controller: str, scenario: Any, ecu: str, bad: BadInput,
         output: Path) -> tuple[Any, BaseException | None, int | None, int | None]:
    """The case's run: (result or None, the error that ended it or None, the ECU's exit
    status, frames the ECU sent before the run for a refusal case, else None)."""
    from hil.bus import BusConfig, private_virtual_channel
    from hil.ecu_runners import EcuProcess
    from hil.rig import Rig, RigHooks
    from hil.run_types import RunOptions, SessionError
    from hil.time_master import TimeMasterError
    from hil.timing.hub import READY_DELAY_S

    refusal = case.ecu_fault["expect"] == "refused"
    options = RunOptions(controller, BusConfig("virtual", private_virtual_channel("faults")),
                         handshake_timeout_s=START_TIMEOUT_S, ack_timeout_s=10.0, ecu_output=output,
                         model=bad.model, excite=bad.excite, ecu=ecu)
    listeners: list[can.BusABC] = []

    def start_ecu(rig: Rig) -> EcuProcess:
        if refusal:   # hears every frame from the ECU's start on, the handshake's too
            listeners.append(rig.open_bus())
            time.sleep(2 * READY_DELAY_S)
        command, environment = _ecu_command(rig, ecu, bad)
        return EcuProcess(scenario, options, command, environment)

    rig = Rig(scenario, options, RigHooks(ecu=start_ecu, own_hub=True))
    result, error, sent = None, None, None
    try:
        with rig:
            if not refusal:
                rig.run()
            else:
                try:
                    rig.master.handshake()   # answered: the ECU started
                finally:
                    sent = _drain(listeners[0])   # while the hub is still up
        result = None if refusal else rig.result()
    except (TimeMasterError, SessionError) as e:
        if rig.ecu is None:   # no ECU process was started: the harness's fault, not a verdict
            raise
        error = e   # the ECU exited or stalled: judged by the caller
    finally:
        for listener in listeners:
            listener.shutdown()
    return result, error, rig.ecu.process.returncode, sent


def _judge_refusal(case: FaultCase, controller: str, description: str, status: int | None,
                   output: str, sent: int | None, error: BaseException | None, says: str) -> Verdict:
    """The verdict of a case whose ECU must refuse to start (see the module docstring)."""
    from hil.time_master import HandshakeTimeoutError

    lines = output.splitlines()
    started = error is None
    hung = isinstance(error, HandshakeTimeoutError)   # neither refused nor started: stopped here
    verdict = Verdict(case.name, case.group, controller, description, mode_sequence="-")
    verdict.expects = [
        {"expect": "refused at start: exit status 2", "why": "an input it cannot use is an error "
         "before the bus opens", "at_ms": None, "shown": "started" if started else f"exit {status}",
         "met": not started and status == EXIT_USAGE},
        {"expect": "one error line naming the fault", "why": "one `error:` line, no traceback",
         "at_ms": None, "shown": " / ".join(lines)[-300:] or "no output",
         "met": len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0]},
        {"expect": "no frame sent", "why": "refused before the bus opens", "at_ms": None,
         "shown": f"{sent} frames", "met": not started and sent == 0},
    ]
    if started or hung:
        verdict.outcome = "STARTED" if started else "no answer"
    elif status is not None and status < 0:   # killed by a signal: a crash, not a refusal
        verdict.crashes, verdict.outcome = 1, "CRASH"
        verdict.crash_reason = f"the ECU died of signal {-status}: {error}"
    else:
        verdict.outcome = "refused to start" if status == EXIT_USAGE else f"exit {status}"
    return verdict


def _fault_rows(result: Any, output: str, says: str) -> list[dict[str, Any]]:
    """The rows of a case whose ECU must latch FAULT at start-up (see the module docstring);
    ``result`` None (the run raised): no task seen, every row missed."""
    trace = result.ecu_trace if result is not None else {"ctrl_mode": np.zeros(0), "cmd_valid": np.zeros(0)}
    modes = trace["ctrl_mode"].astype(int)
    valid = int(np.sum(trace["cmd_valid"] != 0))
    faulted = int(np.sum(modes == int(CtrlMode.FAULT)))
    line = next((text[text.index("FAULT latched"):] for text in output.splitlines()
                 if "FAULT latched" in text), "")   # without the log's time stamp
    return [
        {"expect": "FAULT at every control task", "why": "a bad input file latches FAULT (contract)",
         "at_ms": None, "shown": f"{faulted} of {len(modes)} tasks",
         "met": len(modes) > 0 and faulted == len(modes)},
        {"expect": "CMD_VALID = 0 throughout", "why": "no command from an ECU in FAULT", "at_ms": None,
         "shown": f"{valid} of {len(modes)} commands valid", "met": len(modes) > 0 and valid == 0},
        {"expect": "its FAULT line names the fault", "why": "the file, the line and the check",
         "at_ms": None, "shown": line[-300:] or "no FAULT line", "met": says in line},
    ]


def _safe_stop_rows(result: Any) -> list[dict[str, Any]]:
    """The rows of a case whose controller falls back on every step (see the module
    docstring); ``result`` None (the run raised): no task seen, every row missed."""
    fields = ("time", "ctrl_mode", "cmd_valid", "steer_angle_cmd", "drive_torque_cmd", "faults")
    trace = result.ecu_trace if result is not None else {key: np.zeros(0) for key in fields}
    times_ms = np.round(trace["time"] * 1000).astype(int)
    modes = trace["ctrl_mode"].astype(int)
    law = (modes == int(CtrlMode.ACTIVE)) | (modes == int(CtrlMode.DEGRADED))
    fallbacks = np.flatnonzero(law & ((trace["faults"].astype(int) >> 2) & 1 == 1))
    stops = np.flatnonzero(modes == int(CtrlMode.SAFE_STOP))
    first = int(stops[0]) if len(stops) else len(modes)
    reaction = (int(times_ms[first] - times_ms[fallbacks[0]])
                if len(fallbacks) and len(stops) and first > fallbacks[0] else None)
    stopping = (modes[first:] == int(CtrlMode.SAFE_STOP)) & (trace["cmd_valid"][first:] != 0)
    # the safe stop's steering, from the last command before it
    steer = trace["steer_angle_cmd"][max(first - 1, 0):] if len(stops) else np.zeros(0)
    step = float(np.max(np.abs(np.diff(steer)), initial=0.0))
    towards_straight = bool(np.all(np.abs(steer[1:]) <= np.abs(steer[:-1]) + 1e-9))
    torque = float(np.max(trace["drive_torque_cmd"][first:], initial=0.0))
    return [
        {"expect": f"SAFE_STOP <= {CONTROLLER_FAILED_BOUND_MS} ms after the first fallback",
         "why": "a fallback on 4 control tasks in a row is a failing controller (contract rev. 2)",
         "at_ms": reaction, "met": reaction is not None and reaction <= CONTROLLER_FAILED_BOUND_MS},
        {"expect": "SAFE_STOP to the end, CMD_VALID = 1",
         "why": "left only through STANDBY: the planner's ENGAGE = 1 does not re-engage", "at_ms": None,
         "shown": f"{int(np.sum(stopping))} of {len(stopping)} tasks from the first SAFE_STOP",
         "met": len(stopping) > 0 and bool(np.all(stopping))},
        {"expect": "steer towards straight <= 0.2 rad/s, no drive torque", "why": "the SAFE_STOP command",
         "at_ms": None, "shown": f"largest step {step:.4f} rad, largest torque {torque:.1f} N m",
         "met": len(stopping) > 0 and step <= SAFE_STOP_STEER_STEP_RAD and towards_straight and torque <= 0.0},
    ]


def run_input_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
                   duration_s: float | None = None, ecu: str = "python") -> Verdict:
    """Run an input-file case against ``ecu`` ("python", "c") and judge it by the verdict
    the case expects (``case.ecu_fault["expect"]``: "refused", "fault" or "safe_stop")."""
    from hil.scenario import load_scenario
    from hil.session import reference_path

    fault = case.ecu_fault
    assert fault is not None and fault["kind"] == "input"
    scenario = load_scenario(scenario_name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    description = f"{case.name}: {case.note}"
    with tempfile.TemporaryDirectory(prefix="fault-input-") as folder:
        bad = write_bad_input(fault["defect"], Path(folder), Path(scenario.path_file), ecu)
        output_file = Path(folder) / "ecu.txt"
        result, error, status, sent = _run(case, controller, scenario, ecu, bad, output_file)
        output = output_file.read_text(errors="replace") if output_file.is_file() else ""
        # the report names the files without this run's temporary folder: the same every run
        output = output.replace(f"{folder}{os.sep}", "")
    says = fault["says"].format(file=bad.file.name)
    if fault["expect"] == "refused":
        verdict = _judge_refusal(case, controller, description, status, output, sent, error, says)
    else:
        unexpected = sum("unexpected error" in line for line in output.splitlines())
        verdict = evaluate(case, controller, result, error, unexpected, 0, description,
                           reference_path(scenario), onset_ms=0, frames_hit=1)
        if fault["expect"] == "safe_stop":   # the usual outcome: a safe stop, at standstill
            verdict.expects.extend(_safe_stop_rows(result))
        else:
            verdict.expects.extend(_fault_rows(result, output, says))
            if verdict.crashes == 0 and verdict.expects_met:
                verdict.outcome = "FAULT latched"
    verdict.ecu = ecu
    return verdict

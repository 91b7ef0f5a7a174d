"""The fault campaign's harness for the C ECU executable (``--ecu c``, ``make faults-c``):
which cases cannot reach a separate ECU process (`c_not_applicable`, reported as not
applicable with the reason), and the ECU-level cases (`run_c_ecu_case`) against the
process on a loopback socketcand hub of its own. The lost bus drops the process's
connection at a relay (``hil.fault_cases.relay.DroppingRelay``) and watches its output and
CPU time (`_lose_c_bus`). A crash of the C ECU is the run raising (the process exited or
stopped ACKing); it has no Python exceptions to count.
"""
from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

from hil.fault_cases.catalogue import SCENARIO, FaultCase
from hil.fault_cases.relay import DroppingRelay
from hil.fault_cases.verdicts import LostBusProbe, Verdict, evaluate, jump_tasks_expect

#: Look-alike frame kinds the C ECU's loopback socketcand hub cannot carry as themselves.
HUB_LOST_KINDS = ("fd", "remote", "error")


def c_not_applicable(case: FaultCase) -> str | None:
    """Why ``case`` cannot run against the C ECU (a separate process), or None when it can."""
    kinds = sorted({f.get("frame_kind") for f in case.table.get("bus", ())
                    if f.get("kind") == "lookalike"} & set(HUB_LOST_KINDS))
    if kinds:
        return (f"{' / '.join(kinds)} frames cannot reach a separate ECU process here: socketcand's "
                "raw-mode protocol, which the loopback hub speaks, has no FD, remote or error flag "
                "(python-can sends FD and error frames as classic data frames, which would be "
                "contract frames, and refuses a remote frame without data); the C ECU's receive "
                "path drops them by kind (tests/test_firmware_c_rx.py, the fuzz through libecu.so)")
    return None


def _process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process ``pid`` so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _lose_c_bus(ecu: Any, relay: DroppingRelay, outage_s: float) -> LostBusProbe:
    """`_lose_bus` (``hil.fault_cases.python_ecu``) for the C ECU process: its bus taken away
    at the relay for ``outage_s`` of wall clock, watched through its output (when it says
    the bus is lost, its log lines, when it says it reopened) and its process CPU time; its
    reopening tries are the connections the relay refused."""
    probe = LostBusProbe(recv_calls=None)
    output = Path(ecu.output_path)
    offset = len(output.read_bytes())

    def said() -> str:
        return output.read_bytes()[offset:].decode(errors="replace")

    started = time.monotonic()
    relay.lose()
    cpu_from = wall_from = None
    while time.monotonic() - started < outage_s:
        if cpu_from is None and "bus lost" in said():
            wall_from = time.monotonic()
            cpu_from = _process_cpu_s(ecu.process.pid)
            probe.noticed_ms = 1000 * (wall_from - started)
        time.sleep(0.005)
    if cpu_from is not None:
        probe.lost_wall_s = time.monotonic() - wall_from
        probe.cpu_fraction = (_process_cpu_s(ecu.process.pid) - cpu_from) / probe.lost_wall_s
    lines = said().splitlines()
    probe.log_lines = len(lines)
    probe.lost_lines = sum("bus lost" in line or "still lost" in line for line in lines)
    probe.reopen_tries = relay.refused
    relay.back()
    back_at = time.monotonic()
    while time.monotonic() - back_at < 3.0 and "bus reopened" not in said():
        time.sleep(0.005)
    if "bus reopened" in said():
        probe.reopened_ms = 1000 * (time.monotonic() - back_at)
    return probe


def run_c_ecu_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
                   duration_s: float | None = None) -> Verdict:
    """A fault of the time base or of the ECU's own bus against the C ECU: the rig of
    ``hil.session.run_hil`` for ``--ecu c`` (``hil.rig.Rig``: the executable on a loopback
    socketcand hub of its own); the time master's bus wrapped in `TimeShiftingBus` (time
    jump), or the ECU's connection through a `DroppingRelay` (lost bus); judged as
    `run_ecu_case` judges the Python ECU's run, the lost bus by the same rules from the
    process's output and CPU time."""
    from hil.fault_buses import TimeShiftingBus, time_jump_wrapper
    from hil.rig import Rig, RigHooks
    from hil.scenario import load_scenario
    from hil.session import EcuProcess, SessionError, c_ecu_command, default_options, reference_path
    from hil.time_master import TimeMasterError
    from hil.timing.hub import READY_DELAY_S

    fault = case.ecu_fault
    assert fault is not None and fault["kind"] in ("time_jump", "lost_bus")
    scenario = load_scenario(scenario_name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    onset_ms = round(fault["start_s"] * 1000)
    options = default_options(controller, ecu="c")
    relays: list[DroppingRelay] = []
    shifted: list[TimeShiftingBus] = []
    probes: list[LostBusProbe] = []

    def start_ecu(rig: Rig) -> EcuProcess:
        if fault["kind"] == "lost_bus":  # the executable connects through the relay
            relays.append(DroppingRelay(rig.hub_port))
        port = relays[0].port if relays else rig.hub_port
        return EcuProcess(scenario, options, c_ecu_command(scenario, options, port))

    rig: Rig | None = None

    def before_tick(tick_ms: int) -> None:
        if relays and tick_ms == onset_ms:
            probes.append(_lose_c_bus(rig.ecu, relays[0], fault["outage_s"]))
            time.sleep(2 * READY_DELAY_S)   # the reopened connection is a new client of the hub

    error, result = None, None
    rig = Rig(scenario, options, RigHooks(ecu=start_ecu, wrap_master_bus=time_jump_wrapper(fault, onset_ms, shifted),
                                          before_tick=before_tick))
    try:
        with rig:
            rig.run()
        result = rig.result()
    except (TimeMasterError, SessionError) as e:   # the ECU stalled or died: a result of the case
        error = e
    finally:
        for relay in relays:
            relay.close()
    frames_hit = shifted[0].record.actions if shifted else 1
    verdict = evaluate(case, controller, result, error, 0, 0, f"{case.name}: {case.note}",
                       reference_path(scenario), onset_ms=onset_ms, frames_hit=frames_hit)
    verdict.ecu = "c"
    if result is not None and fault["kind"] == "time_jump":
        verdict.expects.append(jump_tasks_expect(result.extra["ecu_frames_raw"], onset_ms))
    elif probes:
        verdict.expects.extend(probes[0].expects())
    return verdict

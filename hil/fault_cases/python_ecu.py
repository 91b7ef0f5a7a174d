"""The fault campaign's harness for the Python ECU: the ECU-level cases (`run_ecu_case`: a
jump of virtual time, a lost bus) run with the ECU (``firmware_sim.ecu.Ecu``) in a thread
here, the time master's bus or the ECU's own wrapped (``hil.fault_buses``), the lost bus
watched meanwhile (`_lose_bus`); and the count of what the ECU logs (`EcuLogCounter`, for
every run against the Python ECU).
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any

from hil.fault_cases.catalogue import SCENARIO, FaultCase
from hil.fault_cases.verdicts import LostBusProbe, Verdict, evaluate, jump_tasks_expect


class EcuLogCounter(logging.Handler):
    """Counts what the ECU logs: caught exceptions and controller failures."""

    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.unexpected = 0
        self.controller = 0

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if "unexpected error" in text:
            self.unexpected += 1
        elif "controller step raised" in text:
            self.controller += 1


class _LogLines(logging.Handler):
    """Keeps what the ECU logs at WARNING and above (the lost bus's rate limit)."""

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def _lose_bus(ecu: Any, thread: threading.Thread, bus: Any, outage_s: float,
              back: threading.Event, reopen_tries: list[float]) -> LostBusProbe:
    """Take ``bus`` away for ``outage_s`` of wall clock and watch the ECU meanwhile: when
    it notices, its thread's CPU time from then on (a busy loop shows as ~100 %), its log
    lines and reopening tries; then let the bus come back (``back``) and wait for the ECU
    to reopen it."""
    probe = LostBusProbe()
    lines = _LogLines()
    logger = logging.getLogger("firmware_sim")
    logger.addHandler(lines)
    cpu_clock = time.pthread_getcpuclockid(thread.ident)
    started = time.monotonic()
    bus.lose()
    cpu_from = wall_from = None
    try:
        while time.monotonic() - started < outage_s:
            if cpu_from is None and ecu.bus_lost:
                wall_from = time.monotonic()
                cpu_from = time.clock_gettime(cpu_clock)
                probe.noticed_ms = 1000 * (wall_from - started)
            time.sleep(0.005)
        if cpu_from is not None:
            probe.lost_wall_s = time.monotonic() - wall_from
            probe.cpu_fraction = (time.clock_gettime(cpu_clock) - cpu_from) / probe.lost_wall_s
        probe.log_lines = len(lines.lines)
        probe.lost_lines = sum("bus lost" in line or "still lost" in line for line in lines.lines)
        probe.reopen_tries = len(reopen_tries)
        probe.recv_calls = bus.calls_while_lost
    finally:
        logger.removeHandler(lines)
    back.set()
    back_at = time.monotonic()
    while time.monotonic() - back_at < 3.0 and not ecu.bus_reopened:
        time.sleep(0.005)
    if ecu.bus_reopened:
        probe.reopened_ms = 1000 * (time.monotonic() - back_at)
    return probe


def run_ecu_case(case: FaultCase, controller: str, scenario_name: str = SCENARIO,
                 duration_s: float | None = None) -> Verdict:
    """Run a fault of the time base or of the ECU's own bus (``case.ecu_fault``): the rig
    of ``hil.session.run_hil`` (``hil.rig.Rig``) in lockstep on a private virtual bus, with
    the ECU in a thread here so that its bus (`LosableBus`) or the master's
    (`TimeShiftingBus`) can be wrapped; judged as `evaluate` judges every run, plus the
    case's own measurements."""
    from firmware_sim.ecu import Ecu
    from hil.bus import BusConfig, private_virtual_channel
    from hil.ecu_runners import EcuRunner
    from hil.fault_buses import BusDownError, LosableBus, TimeShiftingBus, time_jump_wrapper
    from hil.rig import Rig, RigHooks
    from hil.scenario import load_scenario
    from hil.session import default_options, reference_path
    from hil.time_master import TimeMasterError

    fault = case.ecu_fault
    assert fault is not None
    scenario = load_scenario(scenario_name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    onset_ms = round(fault["start_s"] * 1000)
    options = default_options(controller, BusConfig("virtual", private_virtual_channel("faults")),
                              ack_timeout_s=5.0)
    back = threading.Event()
    reopen_tries: list[float] = []
    shifted: list[TimeShiftingBus] = []
    probes: list[LostBusProbe] = []

    class ThreadEcu(EcuRunner):
        """The Python ECU in a thread on a bus this case can take away."""

        def __init__(self, rig: Rig) -> None:
            def reopen() -> Any:
                reopen_tries.append(time.monotonic())
                if not back.is_set():
                    raise BusDownError("CAN interface still down")
                return rig.open_bus()

            self.bus = LosableBus(rig.open_bus())
            self.ecu = Ecu(self.bus, controller, {scenario.path_id: scenario.path_file}, lockstep=True,
                           reopen_bus=reopen)
            self.stop_event = threading.Event()
            self.thread = threading.Thread(target=self.ecu.run, args=(self.stop_event,),
                                           name="ecu-fault-case", daemon=True)
            self.thread.start()

        def alive_problem(self) -> str | None:
            return None if self.thread.is_alive() else "ECU thread ended"

        def stop(self) -> None:
            self.stop_event.set()
            self.thread.join(5.0)
            self.ecu.close()   # it shuts down its own bus (the reopened one too)

    rig: Rig | None = None

    def before_tick(tick_ms: int) -> None:
        if fault["kind"] == "lost_bus" and tick_ms == onset_ms:
            ecu = rig.ecu
            probes.append(_lose_bus(ecu.ecu, ecu.thread, ecu.bus, fault["outage_s"], back, reopen_tries))

    counter = EcuLogCounter()
    logging.getLogger("firmware_sim").addHandler(counter)
    error, result = None, None
    rig = Rig(scenario, options, RigHooks(ecu=ThreadEcu, wrap_master_bus=time_jump_wrapper(fault, onset_ms, shifted),
                                          before_tick=before_tick))
    try:
        with rig:
            rig.run()
    except TimeMasterError as e:   # the ECU stalled or died: a result of the case
        error = e
    finally:
        logging.getLogger("firmware_sim").removeHandler(counter)
    if error is None:
        result = rig.result()
    frames_hit = shifted[0].record.actions if shifted else 1
    verdict = evaluate(case, controller, result, error, counter.unexpected, counter.controller,
                       f"{case.name}: {case.note}", reference_path(scenario), onset_ms=onset_ms,
                       frames_hit=frames_hit)
    if fault["kind"] == "time_jump":
        verdict.expects.append(jump_tasks_expect(rig.monitor.raw, onset_ms))
    elif probes:
        verdict.expects.extend(probes[0].expects())
    return verdict

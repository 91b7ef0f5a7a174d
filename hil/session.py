"""One HIL run over CAN: the ECU, the plant, the planner, a time master and a recorder on
one bus, for one scenario and one controller.

Where the ECU runs depends on the bus:

- python-can's ``virtual`` interface exists only inside one process, so the ECU runs
  in-process: its own bus object and ``firmware_sim.ecu.Ecu`` in a thread;
- any other interface (SocketCAN ``vcan0``, a real adapter) gets the ECU as a separate
  process through its CLI (``eso-ecu``: ``python -m firmware_sim ...``), stopped with SIGTERM at the
  end. Only CAN frames pass between the two, as on a vehicle.

``RunOptions.ecu`` "c" runs the C ECU executable (``build/firmware/ecu``, ``make
firmware``; docs/firmware.md) as that process instead. It speaks SocketCAN and socketcand
only, so on the ``virtual`` interface the run moves to a socketcand hub of its own on TCP
loopback (``hil.timing.hub``, as the firmware's bus tests): every node of this process and
the executable are its clients.

Results: the plant's true time series (5 ms ticks), the ECU's frames per control cycle,
the tracking metrics of hil/metrics.py on the true pose at the control instants (every
25 ms, as studies/closed_loop.py computes them), and the frame log of the recorder.
"""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from can_defs.frames import CtrlMode
from hil.bus import BusConfig, open_bus, private_virtual_channel
from hil.errors import HilError
from hil.logio import LogMetadata, write_sidecar
from hil.metrics import PathErrors, TrackingMetrics, path_errors, tracking_metrics
from hil.plant_node import PlantNode
from hil.planner_node import PlannerNode, engage_from_start
from hil.recorder import BusRecorder, EcuFrameMonitor
from hil.scenario import Scenario
from hil.time_master import (DEFAULT_ACK_TIMEOUT_S, DEFAULT_HANDSHAKE_TIMEOUT_S,
                             LockstepMaster, MasterStats, RealTimeMaster)

#: Control period of the ECU (contract: 25 ms); metrics are sampled at these instants.
CONTROL_PERIOD_MS = 25
#: Wall-clock wait for a stopped ECU process before it is killed.
ECU_STOP_TIMEOUT_S = 5.0
#: Root of the checkout (the ECU process runs from here).
REPO_ROOT = Path(__file__).resolve().parent.parent
#: The C ECU executable (``make firmware``), for ``RunOptions.ecu`` "c".
C_ECU_EXECUTABLE = REPO_ROOT / "build" / "firmware" / "ecu"
#: ECU implementations a run can use: firmware_sim (Python) and the C executable.
ECU_IMPLEMENTATIONS = ("python", "c")
#: Controllers the C ECU has (firmware_sim.native.NATIVE_CONTROLLERS).
C_ECU_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: Channel name on a run's own socketcand hub (the hub routes by channel name only).
HUB_CHANNEL = "vcan0"


class SessionError(HilError):
    """The HIL run could not be set up or its ECU failed."""


@dataclass(frozen=True)
class RunOptions:
    """How to run one scenario over CAN.

    ``lockstep`` False runs on the wall clock. ``log_path`` None records nothing.
    ``engage`` overrides the planner's engage schedule (virtual time s -> bool).
    ``ecu_output`` is where a separate ECU process writes stdout/stderr (default: a
    temporary file, shown in errors). ``faults`` (a ``hil.faults.FaultSpec``) puts a
    fault injector between the HIL nodes and the bus and changes the plant; what it did
    is in ``HilRunResult.extra["injector"]`` (its ``records()``).
    """

    controller: str
    bus: BusConfig
    lockstep: bool = True
    log_path: Path | None = None
    handshake_timeout_s: float = DEFAULT_HANDSHAKE_TIMEOUT_S
    ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S
    engage: Callable[[float], bool] = engage_from_start
    ecu_output: Path | None = None
    ecu_extra_args: tuple[str, ...] = ()
    #: Faults to inject (``hil.faults.FaultSpec``); None injects nothing.
    faults: Any = None
    #: Builds the in-process ECU's controller from its name (``firmware_sim.ecu.Ecu``'s
    #: ``controller_factory``; e.g. another model artefact); None: the registry. Only on
    #: the virtual bus: a separate ECU process builds its own.
    controller_factory: Callable[[str], Any] | None = None
    #: The ECU's ``--model`` (another model file) and ``--excite`` (identification
    #: excitation program), passed to the in-process ECU or to the ECU process alike.
    model: Path | None = None
    excite: str | None = None
    #: Which ECU: "python" (firmware_sim) or "c" (the executable ``C_ECU_EXECUTABLE``, a
    #: process; on the virtual interface the run uses a loopback socketcand hub).
    ecu: str = "python"


@dataclass
class HilRunResult:
    """Outcome of one run: time series (column -> array (n,)), metrics, run facts."""

    scenario: str
    controller: str
    bus: str
    mode: str
    plant_trace: dict[str, np.ndarray]
    ecu_trace: dict[str, np.ndarray]
    tracking: TrackingMetrics
    stats: MasterStats
    wall_time_s: float
    log_path: Path | None = None
    frames_logged: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-ready facts and metrics of the run."""
        ecu = self.ecu_trace
        solve_us = ecu["solve_time_us"][ecu["qp_status"] != 15] if len(ecu["time"]) else []
        active = ecu["ctrl_mode"] == int(CtrlMode.ACTIVE) if len(ecu["time"]) else []
        return {
            "scenario": self.scenario, "controller": self.controller, "bus": self.bus,
            "mode": self.mode, "wall_time_s": round(self.wall_time_s, 3),
            "ticks": self.stats.ticks, "frames_sent": self.stats.frames_sent,
            "frames_received": self.stats.frames_received,
            "realtime_overruns": self.stats.overruns,
            "control_cycles": int(len(ecu["time"])),
            "active_cycles": int(np.sum(active)),
            "solve_time_us_median": float(np.median(solve_us)) if len(solve_us) else None,
            "solve_time_us_max": float(np.max(solve_us)) if len(solve_us) else None,
            "log": str(self.log_path) if self.log_path else None,
            "frames_logged": self.frames_logged,
            "tracking": self.tracking.as_dict(),
        }

    def write(self, out_dir: Path) -> list[Path]:
        """Write ``plant.csv``, ``ecu.csv`` and ``summary.json`` to ``out_dir`` (its parent
        must exist: no folder tree is created silently)."""
        out_dir.mkdir(exist_ok=True)
        written = [_write_csv(out_dir / "plant.csv", self.plant_trace),
                   _write_csv(out_dir / "ecu.csv", self.ecu_trace)]
        summary = out_dir / "summary.json"
        summary.write_text(json.dumps(self.summary(), indent=2) + "\n", encoding="utf-8")
        written.append(summary)
        return written


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    names = list(columns)
    with path.open("w", newline="", encoding="ascii") as handle:
        writer = csv.writer(handle)
        writer.writerow(names)
        for row in zip(*(columns[n] for n in names)):
            writer.writerow([f"{v:.9g}" for v in row])
    return path


# --- the ECU, in-process or as a process -------------------------------------------------


class _EcuRunner:
    """Start / liveness / stop of the ECU, wherever it runs."""

    def alive_problem(self) -> str | None:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError


class InProcessEcu(_EcuRunner):
    """``firmware_sim.ecu.Ecu`` on its own virtual bus object, run in a thread."""

    def __init__(self, scenario: Scenario, options: RunOptions) -> None:
        from firmware_sim.controller_factory import model_controller_factory
        from firmware_sim.ecu import Ecu  # the ECU package: only needed in-process
        from firmware_sim.excitation import load_excitation

        self._bus = open_bus(options.bus)
        try:
            self.ecu = Ecu(self._bus, options.controller, {scenario.path_id: scenario.path_file},
                           lockstep=options.lockstep, clock=time.monotonic,
                           controller_factory=options.controller_factory
                           or model_controller_factory(options.controller, options.model),
                           excitation=load_excitation(options.excite))
        except Exception as e:
            self._bus.shutdown()
            raise SessionError(f"cannot start the ECU with controller "
                               f"'{options.controller}': {e}") from e
        if self.ecu.load_error:
            # The ECU latches FAULT for this (contract); a run could only show CMD_VALID = 0.
            self.ecu.close()
            raise SessionError(f"the ECU latched FAULT at start-up: {self.ecu.load_error}")
        self._stop_event = threading.Event()
        self._failure: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="ecu", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.ecu.run(self._stop_event)
        except BaseException as e:  # noqa: BLE001 - reported to the master via alive_problem
            self._failure = e

    def alive_problem(self) -> str | None:
        if self._failure is not None:
            return f"ECU thread raised {self._failure!r}"
        if not self._thread.is_alive():
            return "ECU thread ended"
        return None

    def stop(self) -> None:
        self._stop_event.set()
        self._thread.join(timeout=ECU_STOP_TIMEOUT_S)
        try:
            self.ecu.close()
        finally:
            self._bus.shutdown()


def ecu_command(scenario: Scenario, options: RunOptions) -> list[str]:
    """Command line of the ECU process for this run (firmware_sim's CLI)."""
    return [sys.executable, "-m", "firmware_sim",
            "--interface", options.bus.interface, "--channel", options.bus.channel,
            "--controller", options.controller,
            "--path", f"{scenario.path_id}={scenario.path_file}",
            "--lockstep" if options.lockstep else "--realtime",
            # the ECU process runs in the checkout: files named relative to here, absolute
            *(["--model", str(Path(options.model).resolve())] if options.model is not None else []),
            *(["--excite", _program_argument(options.excite)] if options.excite is not None else []),
            *options.ecu_extra_args]


def _program_argument(excite: str) -> str:
    """``--excite``: a shipped program's name as it is, a program file made absolute."""
    return str(Path(excite).resolve()) if Path(excite).suffix.lower() in (".toml", ".csv") else excite


def check_c_ecu(options: RunOptions) -> None:
    """Whether the C ECU can run ``options`` (before anything is opened or written).

    Raises:
        SessionError: the executable is not built, or the run asks for what the C ECU
            does not have (another controller, a controller factory, an interface other
            than virtual, socketcan, socketcand).
    """
    if not C_ECU_EXECUTABLE.is_file():
        raise SessionError(f"the C ECU {C_ECU_EXECUTABLE} is not built: run make firmware")
    if options.controller not in C_ECU_CONTROLLERS:
        raise SessionError(f"the C ECU has no controller '{options.controller}' (it has "
                           f"{', '.join(C_ECU_CONTROLLERS)}); use the Python ECU")
    if options.controller_factory is not None:
        raise SessionError("a controller factory needs the Python ECU in-process, not the C ECU")
    if not options.bus.is_virtual and options.bus.interface not in ("socketcan", "socketcand"):
        raise SessionError(f"the C ECU speaks socketcan and socketcand only, not {options.bus.interface}")


def c_ecu_command(scenario: Scenario, options: RunOptions, hub_port: int | None = None) -> list[str]:
    """Command line of the C ECU executable for this run (its CLI is firmware_sim's;
    docs/firmware.md). ``hub_port``: the run's own socketcand hub on loopback.

    Raises:
        SessionError: as `check_c_ecu`; ``options.model`` does not convert to its data
            file, or is of another shape than the build's.
    """
    check_c_ecu(options)
    if hub_port is not None:
        bus = ["--interface", "socketcand", "--channel", HUB_CHANNEL, "--host", "127.0.0.1",
               "--port", str(hub_port)]
    else:
        bus = ["--interface", options.bus.interface, "--channel", options.bus.channel,
               *_socketcand_address(options.bus)]
    return [str(C_ECU_EXECUTABLE), *bus, "--controller", options.controller,
            "--path", f"{scenario.path_id}={Path(scenario.path_file).resolve()}",
            "--data", str(_c_ecu_data_file(options)),
            "--lockstep" if options.lockstep else "--realtime",
            *(["--excite", _program_argument(options.excite)] if options.excite is not None else []),
            *options.ecu_extra_args]


def _c_ecu_data_file(options: RunOptions) -> Path:
    """The C ECU's data file: the build's, or ``options.model`` (a Koopman artefact, or a
    fitted bicycle for lmpc) converted once by firmware/tools/ecu_data.py
    (``firmware_sim.native.data_file_for_model``)."""
    from firmware_sim.controller_factory import model_controller_factory
    from firmware_sim.errors import ConfigError
    from firmware_sim.native import DEFAULT_DATA, NativeController, data_file_for_model

    if options.model is None:
        return DEFAULT_DATA
    try:
        # the Python ECU's checks of the file's kind (a Koopman artefact for eso-dkmpc /
        # dkmpc, a fitted bicycle for lmpc), then its data file
        model_controller_factory(options.controller, Path(options.model))
        data = data_file_for_model(Path(options.model).resolve())
        # the executable would latch FAULT on a model of another shape: say so before the run
        NativeController(options.controller, data)
    except (ConfigError, OSError) as e:
        raise SessionError(f"the C ECU's data file: {e}") from e
    return data


def _socketcand_address(bus: BusConfig) -> list[str]:
    """``--host`` / ``--port`` of a socketcand bus from python-can's configuration."""
    if bus.interface != "socketcand":
        return []
    import can

    config = can.util.load_config(config={"interface": bus.interface, "channel": bus.channel})
    return [*(["--host", str(config["host"])] if config.get("host") else []),
            *(["--port", str(config["port"])] if config.get("port") else [])]


class EcuProcess(_EcuRunner):
    """The ECU as a separate process through its CLI; stopped with SIGTERM."""

    def __init__(self, scenario: Scenario, options: RunOptions, command: list[str] | None = None) -> None:
        """``command``: another ECU's command line (the C ECU's); default firmware_sim's."""
        if options.controller_factory is not None:
            raise SessionError("a controller factory needs the ECU in-process (virtual bus); "
                               f"the ECU process on {options.bus.describe()} builds its own")
        self.command = command or ecu_command(scenario, options)
        if options.ecu_output is not None:
            self.output_path = options.ecu_output
        else:
            handle, name = tempfile.mkstemp(prefix="ecu-", suffix=".txt")
            os.close(handle)
            self.output_path = Path(name)
        self._temporary_output = options.ecu_output is None
        self._output = self.output_path.open("wb")
        try:
            self.process = subprocess.Popen(self.command, cwd=REPO_ROOT, stdin=subprocess.DEVNULL,
                                            stdout=self._output, stderr=subprocess.STDOUT)
        except OSError as e:
            self._output.close()
            raise SessionError(f"cannot start the ECU process {self.command}: {e}") from e

    def output_tail(self, n_chars: int = 1500) -> str:
        """Last characters the ECU process printed."""
        try:
            return self.output_path.read_text(errors="replace")[-n_chars:]
        except OSError:
            return ""

    def alive_problem(self) -> str | None:
        code = self.process.poll()
        if code is None:
            return None
        return f"ECU process exited with status {code}; its output:\n{self.output_tail()}"

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=ECU_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._output.close()
        if self._temporary_output and self.process.returncode == 0:
            self.output_path.unlink(missing_ok=True)  # kept only when something went wrong


# --- one run -------------------------------------------------------------------------------


def run_hil(scenario: Scenario, options: RunOptions,
            on_tick: Callable[[int], None] | None = None) -> HilRunResult:
    """Run ``scenario`` with ``options.controller`` over CAN (see the module docstring).

    Raises:
        SessionError: the ECU could not start or stopped.
        hil.bus.BusOpenError, hil.recorder.RecorderError, hil.time_master.TimeMasterError.
    """
    if options.ecu not in ECU_IMPLEMENTATIONS:
        raise SessionError(f"unknown ECU '{options.ecu}' (one of {', '.join(ECU_IMPLEMENTATIONS)})")
    injector = None
    if options.faults is not None:
        from hil.fault_injector import FaultInjector

        injector = FaultInjector(options.faults)
    plant = PlantNode(scenario, vehicle=injector.vehicle(scenario) if injector else None)
    planner = PlannerNode(scenario, engage=options.engage)
    send_hook = injector.outgoing if injector is not None else None
    monitor = EcuFrameMonitor()
    recorder = None
    ecu: _EcuRunner | None = None
    hub, open_run_bus = _run_bus(options)
    try:
        master_bus = open_run_bus()
    except BaseException:
        if hub is not None:
            hub.close()
        raise
    started = time.monotonic()
    try:
        if options.log_path is not None:
            recorder = BusRecorder(open_run_bus(), options.log_path,
                                   virtual_time=options.lockstep)
        if options.ecu == "c":
            ecu = EcuProcess(scenario, options, c_ecu_command(scenario, options, hub and hub.port))
        elif options.bus.is_virtual:
            ecu = InProcessEcu(scenario, options)
        else:
            ecu = EcuProcess(scenario, options)
        if hub is not None:
            from hil.timing.hub import READY_DELAY_S

            # the hub delivers to a client from READY_DELAY_S after its handshake on; in
            # real time there is no handshake to wait for the executable's start-up
            time.sleep(2 * READY_DELAY_S if options.lockstep else 0.5)
        nodes = [plant, planner, monitor]
        if options.lockstep:
            master: LockstepMaster | RealTimeMaster = LockstepMaster(
                master_bus, nodes, handshake_timeout_s=options.handshake_timeout_s,
                ack_timeout_s=options.ack_timeout_s, peer_alive=ecu.alive_problem,
                send_hook=send_hook)
        else:
            master = RealTimeMaster(master_bus, nodes, send_hook=send_hook)
        stats = master.run(scenario.duration_s, on_tick=on_tick)
        if recorder is not None:
            # Every frame the master sent or received is on the bus: let the recorder
            # catch up, so the log is complete.
            recorder.wait_for(stats.frames_sent + stats.frames_received)
    finally:
        try:
            if ecu is not None:
                ecu.stop()
        finally:
            if recorder is not None:
                # a separate ECU's last frame crosses another process (and a hub): wait
                # for a longer quiet spell so the log keeps it
                # (and on an interrupted run the recorder may still be catching up)
                recorder.stop(settle_s=0.1 if isinstance(ecu, InProcessEcu) else 0.3, max_wait_s=5.0)
                # Sidecar so `eso-hil replay LOG` needs no flags.
                write_sidecar(options.log_path, LogMetadata(
                    controller=options.controller,
                    mode="lockstep" if options.lockstep else "realtime",
                    paths={scenario.path_id: str(scenario.path_file)},
                    scenario=scenario.name, wall_start=recorder.wall_start,
                    wall_end=recorder.wall_end))
            master_bus.shutdown()
            if hub is not None:
                hub.close()
    wall = time.monotonic() - started
    plant_trace = plant.trace()
    return HilRunResult(
        scenario=scenario.name, controller=options.controller,
        bus=f"socketcand:{HUB_CHANNEL} (loopback hub)" if hub is not None else options.bus.describe(),
        mode="lockstep" if options.lockstep else "realtime",
        plant_trace=plant_trace, ecu_trace=monitor.trace(),
        tracking=control_instant_metrics(plant_trace, reference_path(scenario)),
        stats=stats, wall_time_s=wall,
        log_path=options.log_path, frames_logged=recorder.count if recorder else 0,
        extra={"plant_commands_rejected": plant.commands_rejected,
               "ecu_frames_undecodable": monitor.undecodable,
               "ecu_frames_raw": monitor.raw, "ecu": options.ecu,
               **({"injector": injector} if injector is not None else {})},
    )


def _run_bus(options: RunOptions) -> tuple[Any, Callable[[], Any]]:
    """(the run's own socketcand hub or None, a function opening one bus object for a node).

    The C ECU on the virtual interface gets a hub on loopback (it cannot join python-can's
    in-process bus); everything else opens ``options.bus``.
    """
    if options.ecu != "c" or not options.bus.is_virtual:
        return None, lambda: open_bus(options.bus)
    from hil.timing.hub import LOOPBACK, LoopbackCanHub

    hub = LoopbackCanHub(port=0).start()
    config = BusConfig("socketcand", HUB_CHANNEL)
    return hub, lambda: open_bus(config, host=LOOPBACK, port=hub.port, tcp_tune=True)


def reference_path(scenario: Scenario) -> Any:
    """The scenario's ``controller.reference.ReferencePath`` (what e_Y is measured to)."""
    from controller.reference import ReferencePath

    return ReferencePath.from_csv(scenario.path_file)


def control_instant_errors(plant_trace: dict[str, np.ndarray], path: Any) -> tuple[np.ndarray, PathErrors]:
    """The true pose's errors to the path at t = 0, 25, 50, ... ms.

    Args:
        plant_trace: the plant node's trace (``time``, ``x``, ``y``, ``yaw``: (n_ticks,)).
        path: the reference path (``controller.reference.ReferencePath``).

    Returns:
        (the control instants (s), shape (k,); their e_Y, heading error and progress, (k,) each).
    """
    time_ms = np.round(plant_trace["time"] * 1000.0).astype(np.int64)
    at_control = time_ms % CONTROL_PERIOD_MS == 0
    pose = np.column_stack([plant_trace["x"][at_control], plant_trace["y"][at_control],
                            plant_trace["yaw"][at_control]])
    return plant_trace["time"][at_control], path_errors(pose, path)


def control_instant_metrics(plant_trace: dict[str, np.ndarray], path: Any) -> TrackingMetrics:
    """e_Y and heading-error statistics of the true pose at t = 0, 25, 50, ... ms
    (:func:`control_instant_errors`)."""
    _, errors = control_instant_errors(plant_trace, path)
    return tracking_metrics(errors.lateral_error, errors.heading_error)


def default_options(controller: str, bus: BusConfig | None = None, **kwargs: Any) -> RunOptions:
    """Options for a run on a private virtual channel (tests, ``make run``)."""
    bus = bus or BusConfig("virtual", private_virtual_channel())
    return RunOptions(controller=controller, bus=bus, **kwargs)

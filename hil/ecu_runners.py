"""The ECU of a HIL run, wherever it runs: :class:`InProcessEcu` (``firmware_sim.ecu.Ecu``
on its own virtual bus object, in a thread) and :class:`EcuProcess` (a separate process:
firmware_sim's command line, or the C ECU executable with :func:`c_ecu_command`). Each is
an :class:`EcuRunner`: started when built, asked whether it still runs, stopped.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path

from hil.bus import BusConfig, open_bus
from hil.run_types import (C_ECU_CONTROLLERS, C_ECU_EXECUTABLE, ECU_STOP_TIMEOUT_S, HUB_CHANNEL,
                           REPO_ROOT, RunOptions, SessionError)
from hil.scenario import Scenario


class EcuRunner:
    """Start / liveness / stop of the ECU, wherever it runs."""

    def alive_problem(self) -> str | None:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError


class InProcessEcu(EcuRunner):
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


class EcuProcess(EcuRunner):
    """The ECU as a separate process through its CLI; stopped with SIGTERM."""

    def __init__(self, scenario: Scenario, options: RunOptions, command: list[str] | None = None,
                 environment: Mapping[str, str] | None = None) -> None:
        """``command``: another ECU's command line (the C ECU's); default firmware_sim's;
        ``environment``: the process's (default this process's)."""
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
                                            stdout=self._output, stderr=subprocess.STDOUT,
                                            env=None if environment is None else dict(environment))
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

"""The HIL rig: the plant, the planner, the ECU frame monitor, a time master, a recorder and
an ECU of any kind on one bus, for one scenario, wired in one place.

Where the ECU runs (``hil.ecu_runners``) follows the options: the Python ECU in-process on
python-can's ``virtual`` bus (a thread with its own bus object), the Python ECU as a
process on any other interface, the C ECU executable as a process (on the ``virtual``
interface through a socketcand hub of the run's own on TCP loopback, ``hil.timing.hub``,
since it cannot join python-can's in-process bus). A study that needs more than a plain run
passes :class:`RigHooks`: its own ECU (a Python ECU whose bus it can take away, or one
another process started), a wrapper around the time master's bus (a jump of virtual time),
a wrapper around the plant node (a plant that reboots), a hook on each tick's outgoing
frames (odd frames added), a probe before each lockstep tick, more time-master nodes (a
command audit).
``hil.session.run_hil`` is the plain run; the fault campaign's ECU-level cases, the
real-time benchmark's plant side and the bus tests of both ECUs use hooks.

Replay (``hil.replay_feed``) is not a rig ECU kind: there the recorded log stands in for
the plant, the planner and the time master. Its input frames, HIL_SYNC included, go as
recorded to a fresh in-process Python ECU, which answers the log's own ticks (or, for a
time-stamped log, is polled on a clock that follows the log's stamps); nothing is
simulated and no master ticks, so there is nothing for a rig to wire.

Use::

    with Rig(scenario, options, hooks) as rig:   # opens the buses, starts the ECU
        rig.run()                                # lockstep or real time, to the end
    result = rig.result()                        # after the rig is closed
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from hil.bus import BusConfig, open_bus
from hil.ecu_runners import EcuProcess, EcuRunner, InProcessEcu, c_ecu_command
from hil.logio import LogMetadata, describe_inputs, write_sidecar
from hil.metrics import control_instant_metrics, reference_path
from hil.plant_node import PlantNode
from hil.planner_node import PlannerNode
from hil.recorder import BusRecorder, EcuFrameMonitor
from hil.run_types import ECU_IMPLEMENTATIONS, HUB_CHANNEL, HilRunResult, RunOptions, SessionError
from hil.scenario import Scenario
from hil.time_master import HilNode, LockstepMaster, MasterStats, RealTimeMaster, SendHook


class NoEcu(EcuRunner):
    """An ECU this rig does not start (another process started it): always alive."""

    def alive_problem(self) -> str | None:
        return None

    def stop(self) -> None:
        pass


@dataclass(frozen=True)
class RigHooks:
    """What a study adds to a plain run; every field may stay None / empty.

    ``ecu``: builds the run's ECU, called once the master's bus is open (``rig.open_bus``
    opens a bus object of the run for it, ``rig.hub_port`` is the run's hub);
    ``wrap_master_bus``: the time master's bus in, the bus the master uses out;
    ``wrap_plant``: the plant node in, the node the master drives in its place out
    (``rig.plant`` stays the plant, for its trace); ``send_hook``: each tick's node frames
    in, the frames that reach the bus out (after the fault injector's, with ``faults``);
    ``before_tick``: called with the tick (ms) before each lockstep tick, after the
    handshake; ``before_run``: called once before the first tick; ``nodes``: more nodes of
    the time master, after the plant, the planner and the monitor; ``own_hub``: a socketcand
    hub of the run's own on loopback for any ECU (default: only for the C ECU on the
    ``virtual`` interface); ``bus_options``: python-can options of every bus object the rig
    opens on ``options.bus`` (a socketcand server's ``host`` and ``port``).
    """

    ecu: Callable[["Rig"], EcuRunner] | None = None
    wrap_master_bus: Callable[[can.BusABC], can.BusABC] | None = None
    wrap_plant: Callable[[PlantNode], HilNode] | None = None
    send_hook: SendHook | None = None
    before_tick: Callable[[int], None] | None = None
    before_run: Callable[[], None] | None = None
    nodes: Sequence[Any] = ()
    own_hub: bool = False
    bus_options: Mapping[str, Any] = field(default_factory=dict)


class Rig:
    """One scenario's nodes, buses and ECU (see the module docstring).

    Args:
        scenario: the run's scenario.
        options: the controller, bus, time base, ECU, faults and log of the run.
        hooks: what a study adds (:class:`RigHooks`).

    Raises:
        SessionError: an unknown ECU in ``options``.
    """

    def __init__(self, scenario: Scenario, options: RunOptions, hooks: RigHooks = RigHooks()) -> None:
        if options.ecu not in ECU_IMPLEMENTATIONS:
            raise SessionError(f"unknown ECU '{options.ecu}' (one of {', '.join(ECU_IMPLEMENTATIONS)})")
        self.scenario, self.options, self.hooks = scenario, options, hooks
        self.injector = None
        if options.faults is not None:
            from hil.fault_injector import FaultInjector

            self.injector = FaultInjector(options.faults)
        self.plant = PlantNode(scenario, vehicle=self.injector.vehicle(scenario) if self.injector else None)
        self.planner = PlannerNode(scenario, engage=options.engage)
        self.monitor = EcuFrameMonitor()
        self.hub: Any = None
        self.master_bus: can.BusABC | None = None
        self.recorder: BusRecorder | None = None
        self.ecu: EcuRunner | None = None
        self.master: LockstepMaster | RealTimeMaster | None = None
        self.stats: MasterStats | None = None
        self._started = 0.0
        self._wall_s = 0.0
        self._frames_logged = 0

    # --- buses ----------------------------------------------------------------------------

    @property
    def uses_hub(self) -> bool:
        """Whether the run gets a socketcand hub of its own (the C ECU on ``virtual``, or
        ``hooks.own_hub``)."""
        return self.hooks.own_hub or (self.options.ecu == "c" and self.options.bus.is_virtual)

    @property
    def hub_port(self) -> int | None:
        """The port of the run's own hub on loopback (None without one)."""
        return None if self.hub is None else self.hub.port

    def open_bus(self) -> can.BusABC:
        """One more bus object of the run (the hub's, or ``options.bus``)."""
        if self.hub is None:
            return open_bus(self.options.bus, **self.hooks.bus_options)
        from hil.timing.hub import LOOPBACK

        return open_bus(BusConfig("socketcand", HUB_CHANNEL), host=LOOPBACK, port=self.hub.port,
                        tcp_tune=True)

    # --- start, run, stop -----------------------------------------------------------------

    def __enter__(self) -> "Rig":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Open the hub, the master's bus, the recorder and the ECU, and build the master;
        on failure everything opened so far is closed again."""
        if self.uses_hub:
            from hil.timing.hub import LoopbackCanHub

            self.hub = LoopbackCanHub(port=0).start()
        try:
            self.master_bus = self.open_bus()
        except BaseException:
            self.close()
            raise
        self._started = time.monotonic()
        try:
            options = self.options
            if options.log_path is not None:
                self.recorder = BusRecorder(self.open_bus(), options.log_path, virtual_time=options.lockstep)
            self.ecu = self._start_ecu()
            if self.hub is not None:
                from hil.timing.hub import READY_DELAY_S

                # the hub delivers to a client from READY_DELAY_S after its handshake on; in
                # real time there is no handshake to wait for the executable's start-up
                time.sleep(2 * READY_DELAY_S if options.lockstep else 0.5)
            bus = self.master_bus if self.hooks.wrap_master_bus is None else \
                self.hooks.wrap_master_bus(self.master_bus)
            plant = self.plant if self.hooks.wrap_plant is None else self.hooks.wrap_plant(self.plant)
            nodes = [plant, self.planner, self.monitor, *self.hooks.nodes]
            send_hook = self._send_hook()
            if options.lockstep:
                self.master = LockstepMaster(
                    bus, nodes, handshake_timeout_s=options.handshake_timeout_s,
                    ack_timeout_s=options.ack_timeout_s, peer_alive=self.ecu.alive_problem,
                    send_hook=send_hook)
            else:
                self.master = RealTimeMaster(bus, nodes, send_hook=send_hook)
        except BaseException:
            self.close()
            raise

    def _send_hook(self) -> SendHook | None:
        """The fault injector's hook, then ``hooks.send_hook`` (either alone, or None)."""
        injector = None if self.injector is None else self.injector.outgoing
        extra = self.hooks.send_hook
        if injector is None or extra is None:
            return injector or extra
        return lambda tick_ms, frames: extra(tick_ms, injector(tick_ms, frames))

    def _start_ecu(self) -> EcuRunner:
        if self.hooks.ecu is not None:
            return self.hooks.ecu(self)
        if self.options.ecu == "c":
            return EcuProcess(self.scenario, self.options,
                              c_ecu_command(self.scenario, self.options, self.hub_port))
        if self.options.bus.is_virtual:
            return InProcessEcu(self.scenario, self.options)
        return EcuProcess(self.scenario, self.options)

    def run(self, duration_s: float | None = None, on_tick: Callable[[int], None] | None = None) -> MasterStats:
        """Run the master for ``duration_s`` (default the scenario's); ``on_tick`` after each
        tick. Raises what the master raises (``hil.time_master.TimeMasterError``: the ECU
        stalled or stopped)."""
        assert self.master is not None, "start the rig first"
        duration_s = self.scenario.duration_s if duration_s is None else duration_s
        if self.hooks.before_run is not None:
            self.hooks.before_run()
        before_tick = self.hooks.before_tick
        if before_tick is None or not isinstance(self.master, LockstepMaster):
            self.stats = self.master.run(duration_s, on_tick=on_tick)
        else:
            self.master.handshake()
            for tick_ms in range(0, round(duration_s * 1000), 5):
                before_tick(tick_ms)
                self.master.tick(tick_ms)
                if on_tick is not None:
                    on_tick(tick_ms)
            self.stats = self.master.stats
        if self.recorder is not None:
            # Every frame the master sent or received is on the bus: let the recorder catch
            # up, so the log is complete.
            self.recorder.wait_for(self.stats.frames_sent + self.stats.frames_received)
        return self.stats

    def close(self) -> None:
        """Stop the ECU, finish the log and its sidecar, close the buses and the hub."""
        try:
            if self.ecu is not None:
                self.ecu.stop()
        finally:
            recorder, self.recorder = self.recorder, None
            if recorder is not None:
                # a separate ECU's last frame crosses another process (and a hub): wait for
                # a longer quiet spell so the log keeps it (and on an interrupted run the
                # recorder may still be catching up)
                recorder.stop(settle_s=0.1 if isinstance(self.ecu, InProcessEcu) else 0.3, max_wait_s=5.0)
                self._write_sidecar(recorder)
                self._frames_logged = recorder.count
            if self.master_bus is not None:
                self.master_bus.shutdown()
                self.master_bus = None
            if self.hub is not None:
                self.hub.close()
                self.hub = None
            if self._started:
                self._wall_s = time.monotonic() - self._started

    def _write_sidecar(self, recorder: BusRecorder) -> None:
        """The log's sidecar, so `eso-hil replay LOG` rebuilds this ECU without flags: the
        ECU, controller, paths, ``--model`` and ``--excite``, and a hash of every file they
        read (`recorded_ecu_files`, with the tuning), so a replay refuses once one has
        changed."""
        from controller.tuning import DEFAULT_TUNING_PATH
        from firmware_sim.excitation import program_file

        options = self.options
        files: list[tuple[str, Any]] = [(f"path {self.scenario.path_id}", self.scenario.path_file)]
        files += recorded_ecu_files(options.controller, options.model, options.ecu)
        excite_file = None if options.excite is None else program_file(options.excite)
        if excite_file is not None:
            files.append(("excite", excite_file))
        files.append(("tuning", DEFAULT_TUNING_PATH))
        write_sidecar(options.log_path, LogMetadata(
            controller=options.controller, mode="lockstep" if options.lockstep else "realtime",
            paths={self.scenario.path_id: str(self.scenario.path_file)},
            scenario=self.scenario.name, wall_start=recorder.wall_start,
            wall_end=recorder.wall_end, ecu=options.ecu,
            model=None if options.model is None else str(options.model),
            excite=options.excite, input_files=describe_inputs(files)))

    def result(self) -> HilRunResult:
        """The run's result (after :meth:`run`; the wall time counts to :meth:`close`)."""
        assert self.stats is not None, "run the rig first"
        plant_trace = self.plant.trace()
        options = self.options
        return HilRunResult(
            scenario=self.scenario.name, controller=options.controller,
            bus=f"socketcand:{HUB_CHANNEL} (loopback hub)" if self.uses_hub else options.bus.describe(),
            mode="lockstep" if options.lockstep else "realtime",
            plant_trace=plant_trace, ecu_trace=self.monitor.trace(),
            tracking=control_instant_metrics(plant_trace, reference_path(self.scenario)),
            stats=self.stats, wall_time_s=self._wall_s or time.monotonic() - self._started,
            log_path=options.log_path, frames_logged=self._frames_logged,
            extra={"plant_commands_rejected": self.plant.commands_rejected,
                   "ecu_frames_undecodable": self.monitor.undecodable,
                   "ecu_frames_raw": self.monitor.raw, "ecu": options.ecu,
                   **({"injector": self.injector} if self.injector is not None else {})},
        )


#: Controllers built on the nominal vehicle parameters of models/vehicle.toml (the
#: bicycle of LMPC and its ablation, NMPC's single-track model, Stanley's axle distance).
#: A fitted bicycle (``--model``) lies over those parameters, so the file is read then too.
VEHICLE_FILE_CONTROLLERS = ("lmpc", "lmpc-eso", "nmpc", "stanley")


def reads_vehicle_file(controller: str) -> bool:
    """Whether building ``controller`` reads models/vehicle.toml: the controllers of
    `VEHICLE_FILE_CONTROLLERS`, and every MPC whose table in the tuning file switches the
    grip envelope on (its rear axle is the nominal one, ``controller.grip_envelope.RearAxle``)."""
    from controller.grip_envelope import envelope_on
    from controller.tuning import MpcTuning, load_tuning

    if controller in VEHICLE_FILE_CONTROLLERS:
        return True
    table = load_tuning().for_controller(controller)
    return isinstance(table, MpcTuning) and envelope_on(table)


def default_model_files(controller: str) -> list[Path]:
    """The model files the registry builds ``controller`` on without ``--model``: the
    Koopman artefact of eso-dkmpc / dkmpc (``.npz``, ``.json``), the DMDc artefact of
    dmdc-eso; none for the others (`VEHICLE_FILE_CONTROLLERS`)."""
    from controller.registry import MODEL_FILE_KINDS

    if controller == "dmdc-eso":
        from models.dmdc_model import DMDC_ARTIFACT
        stem = DMDC_ARTIFACT
    elif MODEL_FILE_KINDS.get(controller) == "koopman":
        from models.koopman_artifact import DEFAULT_ARTIFACT
        stem = DEFAULT_ARTIFACT
    else:
        return []
    return [stem.with_suffix(".npz"), stem.with_suffix(".json")]


def recorded_ecu_files(controller: str, model: Path | str | None,
                       ecu: str = "python") -> list[tuple[str, Path]]:
    """(role, file) of every file the ECU's controller reads as it is built, but the
    tuning: ``--model``'s files ("model"), else the default artefact ("default model"),
    models/vehicle.toml ("vehicle") where `reads_vehicle_file`, and for the C ECU
    without ``--model`` the build's data file ("C ECU data", build/firmware/ecu_data.bin;
    with ``--model`` its data file is converted from the model and the tuning, both
    recorded). A replay runs the Python ECU, which reads the same model files.

    A default file that does not exist is left out: the ECU could not have been built on
    it, and the sidecar is written as the run ends, when an error must not hide the
    run's own.
    """
    from firmware_sim.controller_factory import model_files
    from firmware_sim.native import DEFAULT_DATA
    from models.vehicle_params import DEFAULT_PARAMS_PATH

    if model is not None:  # checked before the run: each of them exists
        files = [("model", file) for file in model_files(controller, Path(model))]
        defaults = []
    else:
        files = []
        defaults = [("default model", file) for file in default_model_files(controller)]
        if ecu == "c":
            defaults.append(("C ECU data", DEFAULT_DATA))
    if reads_vehicle_file(controller):
        defaults.append(("vehicle", DEFAULT_PARAMS_PATH))
    return files + [(role, file) for role, file in defaults if file.is_file()]

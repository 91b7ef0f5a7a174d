"""The ECU node: a thin cyclic executive around the control law.

Each control task (every 25 ms): inputs -> events -> mode transition -> compute (controller,
dead reckoning or safe stop) -> guard -> TX STEER_TORQUE_CMD and CTRL_DIAG. The control law
is the registry's `Controller`; this module holds no control math.

Two time bases (``docs/can-contract.md``, "Timing semantics"):

- lockstep: HIL_SYNC.TICK is the clock. The handshake TICK 0xFFFFFFFF resets it to "before
  tick 0"; each new TICK runs the control task instants in (previous TICK, TICK], sends
  their frames and then HIL_SYNC_ACK; a repeated TICK is acknowledged again, nothing run.
- real time: an injected monotonic clock with absolute release times (``next += period``).

Nothing in `handle_message`, `poll` or `run` raises: faults become mode events and FAULTS
bits, controller exceptions become a guarded fallback command.

Revision 2 of the contract: only classic data frames with 11-bit IDs are contract frames
(CAN FD, extended, remote and error frames are counted and ignored); a plant sample must be
plausible (``rx.py``); a TICK more than 100 ms ahead is a jump of virtual time (adopted,
STANDBY, controller and observer reset, FAULTS bits 1 and 3); a lost bus (end of the
interface's stream, or receive errors for 100 ms) is logged at most once a second and
reopened every second. Lines that could repeat every cycle go through `RateLimitedLog`.
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import select
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from can_defs.frames import CtrlMode, QpStatus

from controller.base import Command, Controller, StepDebug, VehicleSample
from firmware_sim.clock import (HANDSHAKE_TICK, LockstepClock, MonotonicClock, RealtimeSchedule,
                                TickKind, clock_ns)
from firmware_sim.config import (BUS_LOST_AFTER_MS, BUS_REOPEN_INTERVAL_S, NS_PER_MS, NS_PER_S,
                                 EcuConfig)
from firmware_sim.errors import ConfigError
from firmware_sim.excitation import FAILED_PREFIX, Excitation, ExcitationProgram, describe
from firmware_sim.guard import GuardLimits, guard_command
from firmware_sim.modes import VALID_COMMAND_MODES, ModeEvents, transition
from firmware_sim.ratelimit import RateLimitedLog
from firmware_sim.rx import RxKind, RxState
from firmware_sim.safe_stop import safe_stop_command
from firmware_sim.timing import TimingRecorder
from firmware_sim.tx import DiagRecord, FaultBit, OVERRUNS_MAX, Transmitter

_LOG = logging.getLogger(__name__)

ControllerFactory = Callable[[str], Controller]
PathLoader = Callable[[Path], Any]
BusFactory = Callable[[], can.BusABC]

#: Wait of one `bus.recv` in `run`, s: bounds the reaction to ``stop_event``.
RECV_TIMEOUT_S = 0.05


def is_contract_frame_kind(msg: can.Message) -> bool:
    """A classic CAN data frame with an 11-bit ID (contract, rev. 2, "frame kinds")."""
    return not (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id
                or getattr(msg, "is_fd", False))


def stream_ended(bus: can.BusABC) -> bool:
    """Whether a stream-based bus (socketcand over TCP) has reached the end of its stream.

    python-can's socketcand bus returns "no frame" at once when its server has closed the
    connection, so `recv` would spin; the end shows as a readable socket with nothing to
    read. Buses without such a socket never report an end here (their errors do).
    """
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if not isinstance(sock, socket.socket):
        return False
    try:
        if sock.fileno() < 0:
            return True
        readable, _, _ = select.select([sock], [], [], 0)
        return bool(readable) and sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except (OSError, ValueError):
        return True


def _default_controller_factory(name: str) -> Controller:
    from controller.registry import create_controller  # lazy: loads only the named law
    return create_controller(name)


def _path_tracker(path: Any) -> Any:
    """A ``PathTracker`` for e_Y of the excitation's bound; None for a stand-in path of a
    test (the bound is then not checked)."""
    from controller.reference import PathTracker, ReferencePath
    return PathTracker(path) if isinstance(path, ReferencePath) else None


def _default_path_loader(path: Path) -> Any:
    from controller.reference import ReferencePath
    return ReferencePath.from_csv(path)


@dataclass(frozen=True)
class _Request:
    """Actuator request of one cycle before the guard, with what CTRL_DIAG reports of it.

    ``failed``: the law could not give a command (exception, dead reckoning or path error);
    the NaN request is then refused by the guard, which sends the fallback.
    """

    steer_angle: float
    drive_torque: float
    qp_status: QpStatus = QpStatus.NOT_RUN
    iterations: int = 0
    solve_time_s: float = 0.0
    faults: int = 0
    failed: bool = False


class Ecu:
    """The controller node on one python-can bus.

    Args:
        bus: an open python-can bus (the ECU shuts it down in `close`).
        controller_name: registry name (``eso-dkmpc``, ``dkmpc``, ``lmpc``, ``nmpc``).
        paths: PATH_ID (0..255) -> CSV file with header ``x,y,yaw``.
        lockstep: HIL_SYNC drives time when True, else the monotonic ``clock``.
        clock: monotonic clock in seconds (real-time mode; also stamps arrivals there).
        config: thresholds and limits.
        controller_factory / path_loader: injected for tests; default the registry and
            ``ReferencePath.from_csv``.
        reopen_bus: opens the bus again after it was lost (None: the ECU waits, logging
            once a second, until it is stopped).
        excitation: identification excitation superimposed on the law's command while
            ACTIVE (``firmware_sim.excitation``); None: none.

    A failure to create the controller (model load) or to load a path latches FAULT
    (CMD_VALID = 0) instead of raising, as the contract requires. The lockstep handshake is
    answered once loading has finished, also when it failed, so the master sees FAULT.

    Raises:
        ConfigError: a PATH_ID that is not an integer in 0..255.
    """

    def __init__(self, bus: can.BusABC, controller_name: str, paths: Mapping[int, Path],
                 lockstep: bool = True, clock: MonotonicClock = time.monotonic, *,
                 config: EcuConfig | None = None,
                 controller_factory: ControllerFactory | None = None,
                 path_loader: PathLoader | None = None,
                 reopen_bus: BusFactory | None = None,
                 excitation: ExcitationProgram | None = None) -> None:
        self._bus = bus
        self._reopen_bus = reopen_bus
        self._config = config or EcuConfig()
        self._log = RateLimitedLog(_LOG)
        self.lockstep = lockstep
        self._clock = clock
        self._limits = GuardLimits(self._config.steer_limit_rad, self._config.drive_torque_limit_nm)
        self._period_ns = self._config.control_period_ms * NS_PER_MS
        self._tx = Transmitter(bus, self._log)
        self._rx = RxState(log=self._log)
        #: Frames of other kinds than classic 11-bit data frames, ignored (rev. 2).
        self.ignored_frames = 0
        #: The bus is lost (end of stream or persistent receive errors) and not reopened yet.
        self.bus_lost = False
        self.bus_reopened = 0
        self._lockstep_clock = LockstepClock(self._config.control_period_ms,
                                             self._config.max_catch_up_tasks)
        self._schedule = RealtimeSchedule(self._period_ns)
        self.timing = TimingRecorder(self._config.timing_capacity)
        self._closed = False
        self._warned: set[str] = set()
        self._excitation = (None if excitation is None
                            else Excitation(excitation, self._config.control_period_ms / 1000.0))
        self._excitation_tracker: Any = None  # PathTracker of the active path (e_Y bound)
        if excitation is not None:
            _LOG.warning("%s", describe(excitation))
        for path_id in paths:
            if not isinstance(path_id, int) or isinstance(path_id, bool) or not 0 <= path_id <= 255:
                raise ConfigError(f"PATH_ID must be an integer in 0..255, got {path_id!r}")

        self.load_error: str | None = None
        self._controller: Controller | None = None
        self._paths: dict[int, Any] = {}
        try:
            self._controller = (controller_factory or _default_controller_factory)(controller_name)
        except Exception as error:  # any failure to build the model is a latched FAULT
            self.load_error = f"controller {controller_name!r} failed to load: {error}"
        loader = path_loader or _default_path_loader
        for path_id, file in sorted(paths.items()):
            try:
                self._paths[path_id] = loader(Path(file))
            except Exception as error:
                self.load_error = self.load_error or f"PATH_ID {path_id} file {file}: {error}"
        if self.load_error:
            _LOG.error("FAULT latched: %s", self.load_error)
        self._reset_run()
        self.ready = True

    # ---------------------------------------------------------------- state
    def _reset_run(self) -> None:
        """Start of a run (construction, lockstep handshake): no inputs, INIT (or FAULT)."""
        self._rx.reset()
        self._tx.reset_counters()
        self.mode = CtrlMode.FAULT if self.load_error else CtrlMode.INIT
        self._awaiting_disengage = False
        self._previous_valid_steer = 0.0
        self._active_path_id: int | None = None
        self._controller_failing = False
        self._guard_refusing = False
        self._pending_model_reset = False
        self.overruns = 0
        self.cycles = 0
        self._task_now_ns = 0

    @property
    def rx_counts(self) -> dict[str, int]:
        """Frames accepted / rejected, torn sets and samples since the last reset."""
        return dict(self._rx.counts)

    def _warn_once(self, key: str, message: str, *args: object) -> None:
        if key not in self._warned:
            self._warned.add(key)
            _LOG.warning(message, *args)

    # ---------------------------------------------------------------- RX
    def handle_message(self, msg: can.Message) -> None:
        """Process one received frame; in lockstep a HIL_SYNC runs the due tasks. Never raises."""
        try:
            if not is_contract_frame_kind(msg):
                # rev. 2: never taken for the contract frame of the same number, never FAULTS
                self.ignored_frames += 1
                self._log.log("frame-kind", logging.INFO,
                              "non-contract frame ignored (ID 0x%X, fd=%s, extended=%s, "
                              "remote=%s, error=%s)", msg.arbitration_id,
                              getattr(msg, "is_fd", False), msg.is_extended_id,
                              msg.is_remote_frame, msg.is_error_frame)
                return
            arrival_ns = None if self.lockstep else clock_ns(self._clock)
            outcome = self._rx.receive(msg.arbitration_id, bytes(msg.data), arrival_ns)
            if outcome.kind is RxKind.SYNC and outcome.tick is not None:
                if self.lockstep:
                    self._on_tick(outcome.tick)
                else:
                    self._warn_once("sync-in-realtime", "HIL_SYNC ignored in real-time mode")
        except Exception:  # a bug must not stop the node: log it and carry on
            _LOG.exception("unexpected error while handling frame 0x%03X", msg.arbitration_id)

    def _on_tick(self, tick: int) -> None:
        started = time.perf_counter()
        advance = self._lockstep_clock.advance(tick)
        if advance.kind is TickKind.HANDSHAKE:
            self._reset_run()
            self._tx.send_ack(HANDSHAKE_TICK)
            _LOG.info("lockstep handshake answered; before tick 0")
            return
        if advance.kind is TickKind.NOT_SYNCHRONISED:
            self._warn_once("no-handshake", "HIL_SYNC TICK %d before the handshake ignored", tick)
            return
        if advance.kind is TickKind.BACKWARDS:
            self._rx.e2e_error = True
            self._log.log("tick-backwards", logging.WARNING,
                          "HIL_SYNC TICK %d older than the last TICK %s: discarded", tick,
                          self._lockstep_clock.last_tick_ms)
            return
        if advance.kind is TickKind.JUMP:
            self._on_time_jump(tick, advance.skipped)
        now_ns = LockstepClock.to_ns(tick)
        self._rx.stamp_pending(now_ns)
        if advance.kind is TickKind.REPEATED:
            self._tx.send_ack(tick)
            return
        for _ in advance.due_ms:
            self._control_task(now_ns, release_jitter_s=math.nan)
        self._tx.send_ack(tick)
        if time.perf_counter() - started > self._config.control_period_ms / 1000.0:
            self.overruns += 1

    def _on_time_jump(self, tick: int, skipped: int) -> None:
        """A jump of virtual time (contract, rev. 2): STANDBY (FAULT and INIT stay), the
        controller's and observer's memory cleared, the last good sample dropped, FAULTS
        bits 1 and 3 in the next CTRL_DIAG. The skipped task instants are not run."""
        self._log.log("tick-jump", logging.WARNING,
                      "HIL_SYNC TICK %d: virtual time jumped; adopted, %d control instants "
                      "skipped, %s -> STANDBY with the controller reset", tick, skipped,
                      self.mode.name)
        if self.mode not in (CtrlMode.FAULT, CtrlMode.INIT):
            self.mode = CtrlMode.STANDBY
        self._rx.drop_sample()
        self._rx.e2e_error = True
        self._pending_model_reset = True
        self._active_path_id = None  # re-engaging selects the path again (reset included)
        if self._controller is not None:
            try:
                self._controller.reset()
            except Exception as error:  # logged; ACTIVE again only through _select_path
                _LOG.error("controller reset after a jump of virtual time failed: %s", error)

    # ---------------------------------------------------------------- real time
    def poll(self) -> None:
        """Real-time mode: run the control task when its release time has come."""
        if self.lockstep:
            return
        try:
            now_ns = clock_ns(self._clock)
            if self._schedule.next_release_ns is None:
                self._schedule.start(now_ns)
            if not self._schedule.due(now_ns):
                return
            ideal_ns, skipped = self._schedule.release(now_ns)
            self.overruns += skipped
            self._control_task(now_ns, release_jitter_s=(now_ns - ideal_ns) / NS_PER_S)
            if clock_ns(self._clock) > ideal_ns + self._period_ns:
                self.overruns += 1
        except Exception:
            _LOG.exception("unexpected error in the real-time schedule")

    def _recv_timeout(self) -> float:
        if self.lockstep:
            return RECV_TIMEOUT_S
        return min(RECV_TIMEOUT_S, self._schedule.seconds_until_next(clock_ns(self._clock)))

    def run(self, stop_event: threading.Event) -> None:
        """Blocking loop: receive (short timeout), handle, run due tasks, until ``stop_event``.

        A lost bus (the end of the interface's stream, or receive errors that persist for
        100 ms) is neither a crash nor a busy loop: see `_while_bus_lost`.
        """
        failing_since: float | None = None
        while not stop_event.is_set() and not self._closed:
            if self.bus_lost:
                self._while_bus_lost(stop_event)
                failing_since = None
                continue
            try:
                msg = self._bus.recv(self._recv_timeout())
            except (can.CanError, OSError, ValueError) as error:
                if self._closed or getattr(self._bus, "_is_shutdown", False):
                    break
                now = time.monotonic()
                failing_since = now if failing_since is None else failing_since
                self._log.log("recv", logging.WARNING, "bus receive failed: %s", error)
                if now - failing_since >= BUS_LOST_AFTER_MS / 1000.0:
                    self._lose_bus(f"receive errors for {BUS_LOST_AFTER_MS} ms: {error}")
                else:
                    stop_event.wait(0.01)
                self.poll()
                continue
            failing_since = None
            if msg is not None:
                self.handle_message(msg)
            elif stream_ended(self._bus):
                self._lose_bus("end of the interface's stream")
            self.poll()

    def _lose_bus(self, why: str) -> None:
        self.bus_lost = True
        self._bus_lost_why = why
        self._next_reopen_s = time.monotonic() + BUS_REOPEN_INTERVAL_S
        self._log.log("bus-lost", logging.ERROR, "bus lost (%s); %s", why,
                      "reopening it every second" if self._reopen_bus else "waiting")
        try:
            self._bus.shutdown()
        except Exception as error:  # a dead bus may fail to shut down too
            _LOG.debug("shutdown of the lost bus failed: %s", error)

    def _while_bus_lost(self, stop_event: threading.Event) -> None:
        """One wait of the lost-bus state: real-time tasks keep running on their timeouts
        (inputs time out: DEGRADED, SAFE_STOP, STANDBY), the bus is reopened every second,
        and the state is logged at most once a second. In lockstep nothing runs (no tick)."""
        self.poll()
        now = time.monotonic()
        if now >= self._next_reopen_s:
            self._next_reopen_s = now + BUS_REOPEN_INTERVAL_S
            if self._reopen_bus is None:
                self._log.log("bus-lost", logging.ERROR, "bus still lost (%s)", self._bus_lost_why)
            else:
                try:
                    bus = self._reopen_bus()
                except Exception as error:
                    self._log.log("bus-lost", logging.ERROR,
                                  "bus still lost (%s); reopening failed: %s",
                                  self._bus_lost_why, error)
                else:
                    self._bus = bus
                    self._tx.set_bus(bus)
                    self.bus_lost = False
                    self.bus_reopened += 1
                    _LOG.warning("bus reopened after it was lost (%s)", self._bus_lost_why)
                    return
        wait = max(0.0, self._next_reopen_s - now)
        if not self.lockstep:
            wait = min(wait, self._schedule.seconds_until_next(clock_ns(self._clock)))
        stop_event.wait(max(wait, 0.001))

    # ---------------------------------------------------------------- control task
    def _mode_events(self, now_ns: int) -> tuple[ModeEvents, int | None]:
        """Events of this control task and the newest sample's age (ns, None if none)."""
        cfg = self._config
        rx = self._rx
        sample_age = (None if rx.newest_sample_arrival_ns is None
                      else now_ns - rx.newest_sample_arrival_ns)
        fresh = sample_age is not None and sample_age <= cfg.sample_stale_ms * NS_PER_MS
        # a position reference restarted after a gap > 100 ms counts as lost (SAFE_STOP)
        lost = (sample_age is None or sample_age > cfg.sample_lost_ms * NS_PER_MS
                or rx.reference_restarted)
        planner = rx.newest_planner
        planner_ok = (planner is not None and rx.newest_planner_arrival_ns is not None
                      and now_ns - rx.newest_planner_arrival_ns <= cfg.planner_timeout_ms * NS_PER_MS)
        if self._awaiting_disengage and rx.planner_disengaged_seen:
            self._awaiting_disengage = False
        standstill = (fresh and rx.newest_sample is not None
                      and abs(rx.newest_sample.vx) < cfg.standstill_speed_mps)
        events = ModeEvents(
            load_failed=self.load_error is not None, sample_seen=rx.sample_seen,
            sample_fresh=fresh, sample_lost=lost, planner_ok=planner_ok,
            engage=planner is not None and planner.engage,
            path_known=planner is not None and planner.path_id in self._paths,
            rearmed=not self._awaiting_disengage, standstill=standstill)
        return events, sample_age

    def _select_path(self, path_id: int) -> bool:
        """Reset the controller and give it the path (entering ACTIVE or a path change)."""
        assert self._controller is not None
        try:
            self._controller.reset()
            self._controller.set_path(self._paths[path_id])
        except Exception as error:
            self._active_path_id = None
            _LOG.error("controller reset/set_path(PATH_ID %d) failed: %s", path_id, error)
            return False
        self._active_path_id = path_id
        if self._excitation is not None:
            self._excitation.reset()  # a new engagement: the program starts again
            self._excitation_tracker = _path_tracker(self._paths[path_id])
        return True

    def _step_controller(self, sample: VehicleSample) -> tuple[Command | None, StepDebug | None]:
        assert self._controller is not None
        output = io.StringIO()   # what the solver prints (OSQP writes through sys.stdout / stderr)
        try:
            with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
                command, debug = self._controller.step(sample)
        except Exception as error:
            level = logging.DEBUG if self._controller_failing else logging.ERROR
            _LOG.log(level, "controller step raised %s: %s; fallback command",
                     type(error).__name__, error, exc_info=_LOG.isEnabledFor(logging.DEBUG))
            self._controller_failing = True
            return None, None
        finally:
            self._log_solver_output(output.getvalue())
        self._controller_failing = False
        return command, debug

    def _log_solver_output(self, text: str) -> None:
        """Lines the controller or its solver printed in a step: through the rate-limited
        log (one line a second, counting the rest), never straight to stderr every cycle."""
        for line in text.splitlines():
            if line.strip():
                self._log.log("solver-output", logging.WARNING, "solver output: %s", line.strip())

    def _control_task(self, now_ns: int, release_jitter_s: float) -> None:
        """One control cycle: events -> mode -> request -> guard -> TX (never raises)."""
        started = time.perf_counter()
        self.cycles += 1
        self._task_now_ns = now_ns
        events, sample_age = self._mode_events(now_ns)
        previous_mode = self._update_mode(events)
        faults = self._input_faults(events)
        if self._pending_model_reset:  # a jump of virtual time cleared the memories
            faults |= FaultBit.MODEL_RESET
            self._pending_model_reset = False
        request = self._request(previous_mode, events, sample_age)
        faults |= request.faults
        guarded = guard_command(request.steer_angle, request.drive_torque, self._limits,
                                self._previous_valid_steer)
        if guarded.refused is not None:
            faults |= FaultBit.SOLVER_FALLBACK
            if not request.failed:  # a failed law was logged already
                # warn once per run of refusals, not every 25 ms
                level = logging.DEBUG if self._guard_refusing else logging.WARNING
                _LOG.log(level, "guard refused the command: %s", guarded.refused)
        self._guard_refusing = guarded.refused is not None
        self._previous_valid_steer = guarded.steer_angle
        self._tx.send_command(self.mode, self.mode in VALID_COMMAND_MODES,
                              guarded.steer_angle, guarded.drive_torque)
        tx_ns = None if self.lockstep else clock_ns(self._clock)
        self._tx.send_diag(DiagRecord(
            qp_status=request.qp_status, solve_time_s=request.solve_time_s,
            cycle_time_s=time.perf_counter() - started, qp_iter=request.iterations,
            overruns=min(self.overruns, OVERRUNS_MAX), faults=int(faults)))
        self._record_timing(release_jitter_s, time.perf_counter() - started,
                            request.solve_time_s, now_ns, tx_ns)

    def _update_mode(self, events: ModeEvents) -> CtrlMode:
        """Apply the transition; returns the previous mode."""
        previous_mode = self.mode
        self.mode, reasons = transition(previous_mode, events)
        if self.mode is not previous_mode:
            _LOG.info("%s -> %s (%s)", previous_mode.name, self.mode.name,
                      ", ".join(reason.value for reason in reasons))
            if self.mode is CtrlMode.SAFE_STOP:
                # ACTIVE again only after an ENGAGE = 0 received from now on
                self._awaiting_disengage = True
                self._rx.clear_disengage_latch()
        return previous_mode

    def _input_faults(self, events: ModeEvents) -> int:
        """FAULTS bits 0 and 1 of this cycle; starts collecting the next cycle's RX flags."""
        rx = self._rx
        faults = 0
        unknown_path = rx.newest_planner is not None and not events.path_known
        if (not events.sample_fresh or rx.torn or rx.stale or rx.implausible
                or not events.planner_ok or unknown_path):
            faults |= FaultBit.INPUT_TIMEOUT
        if rx.e2e_error:
            faults |= FaultBit.E2E_ERROR
        rx.clear_cycle_flags()
        return faults

    def _request(self, previous_mode: CtrlMode, events: ModeEvents,
                 sample_age_ns: int | None) -> _Request:
        """The actuator request of the current mode, before the guard."""
        if self.mode is CtrlMode.SAFE_STOP:
            cfg = self._config
            stop = safe_stop_command(self._previous_valid_steer, events.standstill,
                                     cfg.control_period_ms / 1000.0,
                                     cfg.safe_stop_steer_rate_rad_s, cfg.safe_stop_brake_torque_nm)
            return _Request(stop.steer_angle, stop.drive_torque)
        if self.mode not in (CtrlMode.ACTIVE, CtrlMode.DEGRADED):
            return _Request(self._previous_valid_steer, 0.0)  # CMD_VALID = 0: hold, no torque
        planner, measurement = self._rx.newest_planner, self._rx.newest_sample
        assert planner is not None and measurement is not None  # guaranteed by the modes
        faults = 0
        if previous_mode not in (CtrlMode.ACTIVE, CtrlMode.DEGRADED) \
                or self._active_path_id != planner.path_id:
            faults |= FaultBit.MODEL_RESET
            if not self._select_path(planner.path_id):
                return _Request(math.nan, math.nan, faults=faults, failed=True)
        sample: VehicleSample | None = VehicleSample.from_measurement(measurement, planner.target_speed)
        if self.mode is CtrlMode.DEGRADED:
            sample = self._predict(sample, sample_age_ns)
        command, debug = self._step_controller(sample) if sample is not None else (None, None)
        if command is None or debug is None:
            return _Request(math.nan, math.nan, faults=faults, failed=True)  # guard -> fallback
        if debug.fallback:
            faults |= FaultBit.SOLVER_FALLBACK
        if debug.observer_reset:
            faults |= FaultBit.MODEL_RESET
        steer, torque = command.steer_angle, command.drive_torque
        if self._excitation is not None:
            steer, torque = self._excite(self._task_now_ns / NS_PER_S, measurement, steer, torque)
        return _Request(steer, torque, self._qp_status(debug),
                        int(debug.iterations), float(debug.solve_time_s), faults)

    def _excite(self, now_s: float, measurement: Any, steer: float, torque: float) -> tuple[float, float]:
        """The law's command with the identification excitation (ACTIVE only) added.
        Never raises: a failure stops the excitation and leaves the law's command."""
        assert self._excitation is not None
        was_stopped = self._excitation.stopped_reason
        try:
            lateral_error = None
            if self._excitation_tracker is not None and self.mode is CtrlMode.ACTIVE:
                lateral_error = self._excitation_tracker.update(
                    measurement.x, measurement.y, measurement.yaw).lateral_error
            excited_steer, excited_torque, status = self._excitation.step(
                now_s, self.mode is CtrlMode.ACTIVE, measurement.vx, lateral_error, steer, torque,
                self._limits.steer_range(), self._limits.torque_range())
        except Exception as error:  # the control task never raises
            self._excitation.stopped_reason = f"{FAILED_PREFIX}{error}"
            _LOG.error("excitation stopped for this engagement: %s", self._excitation.stopped_reason)
            return steer, torque
        if status.stopped_reason is not None and was_stopped is None:
            level = logging.ERROR if status.stopped_reason.startswith(FAILED_PREFIX) else logging.WARNING
            _LOG.log(level, "excitation stopped for this engagement: %s", status.stopped_reason)
        return excited_steer, excited_torque

    def _predict(self, sample: VehicleSample, sample_age_ns: int | None) -> VehicleSample | None:
        from controller.dead_reckoning import predict_sample
        try:
            return predict_sample(sample, (sample_age_ns or 0) / NS_PER_S)
        except ValueError as error:
            _LOG.error("dead reckoning failed: %s", error)
            return None

    @staticmethod
    def _qp_status(debug: StepDebug) -> QpStatus:
        try:
            return QpStatus(int(debug.status))
        except (ValueError, TypeError):
            return QpStatus.NUMERICAL_ERROR

    def _record_timing(self, release_jitter_s: float, task_time_s: float, solve_time_s: float,
                       now_ns: int, tx_ns: int | None) -> None:
        arrival = self._rx.newest_sample_arrival_ns
        if self.lockstep or arrival is None or tx_ns is None:
            input_age = latency = math.nan
        else:
            input_age = (now_ns - arrival) / NS_PER_S
            latency = (tx_ns - arrival) / NS_PER_S
        self.timing.record(release_jitter_s, task_time_s, solve_time_s, input_age, latency,
                           self.overruns, start_time=now_ns / NS_PER_S, mode=int(self.mode))

    # ---------------------------------------------------------------- shutdown
    def _drain_input(self, budget_s: float = 0.2) -> None:
        """Read what is still arriving before the bus is shut down: a TCP-based bus
        (socketcand) closed with unread input is reset by the kernel, and the reset can
        discard the last frame just sent."""
        give_up = time.monotonic() + budget_s
        try:
            while time.monotonic() < give_up and self._bus.recv(0.01) is not None:
                pass
        except Exception:  # a dead bus has nothing to drain
            pass

    def close(self) -> None:
        """Send one last STEER_TORQUE_CMD with CMD_VALID = 0, then shut the bus down.

        The last frame reports STANDBY (FAULT when latched) with the held steering angle and
        zero torque. Idempotent.
        """
        if self._closed:
            return
        self._closed = True
        mode = CtrlMode.FAULT if self.mode is CtrlMode.FAULT else CtrlMode.STANDBY
        if not self.bus_lost:
            try:
                self._tx.send_command(mode, False, self._previous_valid_steer, 0.0)
            except Exception as error:  # the bus must still be shut down
                _LOG.error("last STEER_TORQUE_CMD not sent: %s", error)
            self._drain_input()
        try:
            self._bus.shutdown()
        except Exception as error:
            _LOG.warning("bus shutdown failed: %s", error)

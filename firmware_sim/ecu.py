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
reopened every second; a controller whose step falls back (FAULTS bit 2) on 4 control
tasks in a row is a failing controller: SAFE_STOP. Lines that could repeat every cycle go through `RateLimitedLog`.

Parts, one job each: this module the node (construction, run state, the frames in and the
two time bases that release the control task), `firmware_sim.control_task` (`ControlTask`,
one control cycle) and `firmware_sim.bus_loop` (`BusLoop`: `run`, the lost bus, `close`),
both base classes of `Ecu`.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import can
from can_defs.frames import CtrlMode
# The contract's one frame-kind test (contract, rev. 2, "frame kinds"): a classic CAN data
# frame with an 11-bit ID. Kept under the ECU's name so that a test can swap the test the
# ECU applies for one that takes every frame.
from can_defs.log_reader import is_contract_data_frame

from controller.base import Controller
from firmware_sim.bus_loop import BusLoop
from firmware_sim.clock import (HANDSHAKE_TICK, LockstepClock, MonotonicClock, RealtimeSchedule, SampleRelease,
                                TickKind, clock_ns)
from firmware_sim.config import (MIN_RELEASE_SPACING_NS, NS_PER_MS, NS_PER_S, SAMPLE_WATCHDOG_NS,
                                 SAMPLE_WINDOW_EARLY_NS, EcuConfig, Plausibility)
from firmware_sim.control_task import ControlTask
from firmware_sim.errors import ConfigError
from firmware_sim.excitation import Excitation, ExcitationProgram, describe
from firmware_sim.guard import GuardLimits
from firmware_sim.ratelimit import RateLimitedLog
from firmware_sim.rx import RxKind, RxState
from firmware_sim.timing import TimingRecorder
from firmware_sim.tx import Transmitter

_LOG = logging.getLogger(__name__)

ControllerFactory = Callable[[str], Controller]
PathLoader = Callable[[Path], Any]
BusFactory = Callable[[], can.BusABC]


def _default_controller_factory(name: str) -> Controller:
    from controller.registry import create_controller  # lazy: loads only the named law
    return create_controller(name)


def _default_path_loader(path: Path) -> Any:
    from controller.reference import ReferencePath
    return ReferencePath.from_csv(path)


class Ecu(ControlTask, BusLoop):
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
        self._rx = RxState(Plausibility(sample_period_ms=self._config.plant_sample_period_ms), log=self._log)
        #: Frames of other kinds than classic 11-bit data frames, ignored (rev. 2).
        self.ignored_frames = 0
        #: The bus is lost (end of stream or persistent receive errors) and not reopened yet.
        self.bus_lost = False
        self.bus_reopened = 0
        self._lockstep_clock = LockstepClock(self._config.control_period_ms,
                                             self._config.max_catch_up_tasks)
        self._schedule = RealtimeSchedule(self._period_ns)
        #: Revision 3: the control task released by the plant's samples (None: the clock).
        self._sample_release = (None if self._config.control_release == "clock" else SampleRelease(
            self._period_ns, SAMPLE_WINDOW_EARLY_NS, SAMPLE_WATCHDOG_NS, MIN_RELEASE_SPACING_NS,
            self._config.sample_lost_ms * NS_PER_MS, self._config.plant_sample_period_ms * NS_PER_MS))
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
            budget = getattr(self._controller, "set_time_budget", None)  # test doubles may lack it
            if not lockstep and budget is not None:  # real time: a long solve falls back, no overrun
                budget(self._config.solver_budget_ms / 1000.0)
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
        if self._sample_release is not None:
            self._sample_release.reset()
        self.mode = CtrlMode.FAULT if self.load_error else CtrlMode.INIT
        self._awaiting_disengage = False
        self._previous_valid_steer = 0.0
        self._active_path_id: int | None = None
        self._controller_failing = False
        self._guard_refusing = False
        self._fallback_streak = 0   # control tasks in a row that sent the fallback (rev. 2)
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
            if not is_contract_data_frame(msg):
                # rev. 2: never taken for the contract frame of the same number, never FAULTS
                self.ignored_frames += 1
                self._log.log("frame-kind", logging.INFO,
                              "non-contract frame ignored (ID 0x%X, fd=%s, extended=%s, "
                              "remote=%s, error=%s)", msg.arbitration_id,
                              getattr(msg, "is_fd", False), msg.is_extended_id,
                              msg.is_remote_frame, msg.is_error_frame)
                return
            arrival_ns = None if self.lockstep else clock_ns(self._clock)
            samples_before = self._rx.counts["samples"]
            outcome = self._rx.receive(msg.arbitration_id, bytes(msg.data), arrival_ns)
            if arrival_ns is not None and self._rx.counts["samples"] > samples_before:
                self._on_good_sample(arrival_ns)  # rev. 3 (real time); lockstep: at the TICK
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
        # a good sample of this tick (its frames came before HIL_SYNC): stamped just below
        new_sample = self._rx.newest_sample is not None and self._rx.newest_sample_arrival_ns is None
        self._rx.stamp_pending(now_ns)
        if advance.kind is TickKind.REPEATED:
            self._tx.send_ack(tick)
            return
        release = self._sample_release
        if release is None or not release.anchored:
            for _ in advance.due_ms:   # revision 2's clock (rev. 3: until a sample anchors the grid)
                self._control_task(now_ns, release_jitter_s=math.nan)
                if release is not None:
                    release.note_release(now_ns)
        else:
            self._release_by_watchdog(now_ns)
        if release is not None and new_sample:
            self._on_good_sample(now_ns)
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
        if self._sample_release is not None:  # the grid anchors again at the next sample
            self._sample_release.reset()
        self._fallback_streak = 0    # the controller starts afresh: no failing streak spans the jump
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
            if self._sample_release is not None and self._sample_release.anchored:
                self._release_by_watchdog(now_ns)
                return
            if self._schedule.next_release_ns is None:
                self._schedule.start(now_ns)
            if not self._schedule.due(now_ns):
                return
            ideal_ns, skipped = self._schedule.release(now_ns)
            self.overruns += skipped
            self._control_task(now_ns, release_jitter_s=(now_ns - ideal_ns) / NS_PER_S)
            if self._sample_release is not None:
                self._sample_release.note_release(now_ns)
            if clock_ns(self._clock) > ideal_ns + self._period_ns:
                self.overruns += 1
        except Exception:
            _LOG.exception("unexpected error in the real-time schedule")

    def _seconds_until_release(self, now_ns: int) -> float:
        """Real time: the longest wait before the next release may be due, s."""
        release = self._sample_release
        if release is not None and release.anchored:
            return max(0, release.instant_ns + release.watchdog_ns - now_ns) / NS_PER_S
        return self._schedule.seconds_until_next(now_ns)

    # ---------------------------------------------------------------- revision 3
    def _on_good_sample(self, arrival_ns: int) -> None:
        """A good plant sample set arrived (rev. 3): windows closed by now first (their
        watchdog), then the sample's own release, if it opens one."""
        release = self._sample_release
        if release is None:
            return
        if release.anchored:
            self._release_by_watchdog(arrival_ns)
        if release.on_sample(arrival_ns):
            self._run_released(arrival_ns, release.instant_ns)

    def _release_by_watchdog(self, now_ns: int) -> None:
        """The period watchdog of revision 3: an instant whose window closed without a good
        sample runs now; older unreleased ones are skipped (in real time counted as overruns:
        in lockstep OVERRUNS counts wall clock only, as in revision 2)."""
        assert self._sample_release is not None
        due, skipped = self._sample_release.on_time(now_ns)
        if not self.lockstep:
            self.overruns += skipped
        if due:
            self._run_released(now_ns, self._sample_release.instant_ns - self._period_ns)

    def _run_released(self, released_ns: int, instant_ns: int) -> None:
        """One task released by revision 3 at ``released_ns`` for the control instant
        ``instant_ns`` (release jitter: released - instant, negative for an early sample)."""
        if self.lockstep:
            self._control_task(released_ns, release_jitter_s=math.nan)
            return
        now_ns = clock_ns(self._clock)
        self._control_task(now_ns, release_jitter_s=(released_ns - instant_ns) / NS_PER_S)
        if clock_ns(self._clock) > released_ns + self._period_ns:
            self.overruns += 1

"""One control task of the ECU (every 25 ms): events -> mode transition -> request ->
guard -> TX of STEER_TORQUE_CMD and CTRL_DIAG.

``ControlTask`` is a part of ``firmware_sim.ecu.Ecu`` (a base class of it): the request of
each mode (the controller's step, dead reckoning in DEGRADED, the safe stop), the FAULTS
bits of the cycle, the streak of fallbacks that makes a failing controller (contract rev. 2),
the identification excitation and the cycle's timing record. It works
on the node's state that ``Ecu.__init__`` and ``Ecu._reset_run`` set up (inputs ``_rx``,
transmitter ``_tx``, ``_controller``, ``_paths``, ``_config``, ``mode``); the time bases
that release it are ``Ecu._on_tick`` (lockstep) and ``Ecu.poll`` (real time). It never
raises: a failing law becomes the guard's fallback command.
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any

from can_defs.frames import CtrlMode, QpStatus

from controller.base import Command, StepDebug, VehicleSample
from firmware_sim.clock import clock_ns
from firmware_sim.config import NS_PER_MS, NS_PER_S
from firmware_sim.excitation import FAILED_PREFIX
from firmware_sim.guard import guard_command
from firmware_sim.modes import VALID_COMMAND_MODES, ModeEvents, transition
from firmware_sim.safe_stop import safe_stop_command
from firmware_sim.tx import DiagRecord, FaultBit, OVERRUNS_MAX

#: The ECU's logger: its lines keep the name ``firmware_sim.ecu`` whichever part logs them.
_LOG = logging.getLogger("firmware_sim.ecu")


def _path_tracker(path: Any) -> Any:
    """A ``PathTracker`` for e_Y of the excitation's bound; None for a stand-in path of a
    test (the bound is then not checked)."""
    from controller.reference import PathTracker, ReferencePath
    return PathTracker(path) if isinstance(path, ReferencePath) else None


def _sample_age_s(sample_age_ns: int | None) -> float:
    """The newest sample's age at the task start (ns, from ``_mode_events``: task start minus
    the time its set was complete) in s, the ``VehicleSample.sample_age_s`` the controller
    receives; 0 without a sample. Exactly the C control task's ``(double)age / 1e9``."""
    return 0.0 if sample_age_ns is None else sample_age_ns / NS_PER_S


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


class ControlTask:
    """The control task of ``firmware_sim.ecu.Ecu`` (see the module docstring)."""

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
            rearmed=not self._awaiting_disengage, standstill=standstill,
            controller_failed=self._fallback_streak >= cfg.controller_failed_cycles)
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
        self._count_fallback(faults)
        self._tx.send_command(self.mode, self.mode in VALID_COMMAND_MODES,
                              guarded.steer_angle, guarded.drive_torque)
        tx_ns = None if self.lockstep else clock_ns(self._clock)
        self._tx.send_diag(DiagRecord(
            qp_status=request.qp_status, solve_time_s=request.solve_time_s,
            cycle_time_s=time.perf_counter() - started, qp_iter=request.iterations,
            overruns=min(self.overruns, OVERRUNS_MAX), faults=int(faults)))
        self._record_timing(release_jitter_s, time.perf_counter() - started,
                            request.solve_time_s, now_ns, tx_ns)

    def _count_fallback(self, faults: int) -> None:
        """Consecutive control tasks whose command was the fallback (FAULTS bit 2) while
        the law ran (ACTIVE / DEGRADED): the next task's ``controller_failed`` event (contract
        rev. 2, a failing controller). Any other task ends the streak."""
        law_ran = self.mode in (CtrlMode.ACTIVE, CtrlMode.DEGRADED)
        if law_ran and faults & FaultBit.SOLVER_FALLBACK:
            self._fallback_streak += 1
        else:
            self._fallback_streak = 0

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
        sample: VehicleSample | None = VehicleSample.from_measurement(
            measurement, planner.target_speed, _sample_age_s(sample_age_ns))
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
        """DEGRADED: the sample moved forward to the task start, so its age is then 0 (the
        delay compensation must not move it over the same time again)."""
        from controller.dead_reckoning import predict_sample
        try:
            return replace(predict_sample(sample, _sample_age_s(sample_age_ns)), sample_age_s=0.0)
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

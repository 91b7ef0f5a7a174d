"""TX path of the ECU: STEER_TORQUE_CMD, CTRL_DIAG and HIL_SYNC_ACK onto the bus.

Alive counters come from one `FrameSender` per ECU run (reset by the lockstep handshake so
that a lockstep run is bit-for-bit repeatable). Sending never raises: a bus or encode
error is logged and counted.
"""
from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

import can
from can_defs.codec import FrameSender, encode
from can_defs.errors import CanDefsError
from can_defs.frames import CtrlDiag, CtrlMode, HilSyncAck, QpStatus, SteerTorqueCmd

from firmware_sim.ratelimit import RateLimitedLog

_LOG = logging.getLogger(__name__)

SOLVE_TIME_US_MAX = 0xFFFF
CYCLE_TIME_US_MAX = 0xFFFF
QP_ITER_MAX = 0xFF
OVERRUNS_MAX = 15


class FaultBit(enum.IntFlag):
    """CTRL_DIAG.FAULTS bits (conditions of the current cycle, not latched)."""

    INPUT_TIMEOUT = 1 << 0   # input timeout, stale or torn sample, unknown PATH_ID
    E2E_ERROR = 1 << 1       # an E2E error since the last cycle
    SOLVER_FALLBACK = 1 << 2  # fallback command sent (solver failure, guard, exception)
    MODEL_RESET = 1 << 3     # model or observer reset


def saturate_int(value: float, upper: int) -> int:
    """Round and clamp to 0..upper (non-finite -> upper, negative -> 0)."""
    if value != value or value == float("inf"):
        return upper
    return min(max(int(round(value)), 0), upper)


@dataclass(frozen=True)
class DiagRecord:
    """Content of one CTRL_DIAG (times in seconds before conversion to us)."""

    qp_status: QpStatus
    solve_time_s: float
    cycle_time_s: float
    qp_iter: int
    overruns: int
    faults: int


class Transmitter:
    """Encodes and sends the ECU's frames on one bus."""

    def __init__(self, bus: can.BusABC, log: RateLimitedLog | None = None) -> None:
        self._bus = bus
        self._sender = FrameSender()
        self._log = log or RateLimitedLog(_LOG)
        self.send_errors = 0

    def set_bus(self, bus: can.BusABC) -> None:
        """Send on ``bus`` from now on (a reopened bus after a lost one)."""
        self._bus = bus

    def reset_counters(self) -> None:
        """Restart the alive counters (lockstep handshake)."""
        self._sender = FrameSender()

    def _send(self, arbitration_id: int, data: bytes) -> bool:
        message = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        try:
            self._bus.send(message)
        except (can.CanError, OSError, ValueError) as error:
            self.send_errors += 1
            self._log.log("send", logging.WARNING, "send of 0x%03X failed: %s",
                          arbitration_id, error)
            return False
        return True

    def send_command(self, mode: CtrlMode, cmd_valid: bool, steer_angle: float,
                     drive_torque: float) -> bool:
        """Send STEER_TORQUE_CMD; the values must have passed the guard."""
        frame = SteerTorqueCmd(ctrl_mode=mode, cmd_valid=cmd_valid,
                               steer_angle_cmd=steer_angle, drive_torque_cmd=drive_torque)
        try:
            data = self._sender.encode(frame)
        except CanDefsError as error:
            self.send_errors += 1
            self._log.log("encode-cmd", logging.ERROR,
                          "STEER_TORQUE_CMD not encodable (%s); sending zero command", error)
            try:
                data = self._sender.encode(SteerTorqueCmd(ctrl_mode=mode, cmd_valid=False,
                                                          steer_angle_cmd=0.0,
                                                          drive_torque_cmd=0.0))
            except CanDefsError:
                return False  # no codec at all (an unusable DBC): nothing can be sent
        return self._send(int(SteerTorqueCmd.FRAME_ID), data)

    def send_diag(self, record: DiagRecord) -> bool:
        """Send CTRL_DIAG with every field saturated to its signal range."""
        frame = CtrlDiag(
            qp_status=record.qp_status,
            solve_time_us=saturate_int(record.solve_time_s * 1e6, SOLVE_TIME_US_MAX),
            cycle_time_us=saturate_int(record.cycle_time_s * 1e6, CYCLE_TIME_US_MAX),
            qp_iter=saturate_int(record.qp_iter, QP_ITER_MAX),
            overruns=saturate_int(record.overruns, OVERRUNS_MAX),
            faults=int(record.faults) & 0xF)
        try:
            data = self._sender.encode(frame)
        except CanDefsError as error:
            self.send_errors += 1
            self._log.log("encode-diag", logging.ERROR, "CTRL_DIAG not encodable: %s", error)
            return False
        return self._send(int(CtrlDiag.FRAME_ID), data)

    def send_ack(self, tick: int) -> bool:
        """Send HIL_SYNC_ACK echoing ``tick``."""
        try:
            data = encode(HilSyncAck(tick=tick))
        except CanDefsError as error:
            self.send_errors += 1
            self._log.log("encode-ack", logging.ERROR, "HIL_SYNC_ACK not encodable: %s", error)
            return False
        return self._send(int(HilSyncAck.FRAME_ID), data)

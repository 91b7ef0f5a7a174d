"""Recording what is on the bus.

- `BusRecorder`: every frame on the channel to a log file, through its own bus object (a
  listener like any other node: on the virtual bus it hears all other bus objects, on
  SocketCAN all other sockets) and a `can.Notifier` feeding `can.Logger`. The format
  follows the file suffix as in python-can: ``.log`` candump (the default, readable by
  can-utils' ``canplayer``), ``.asc``, ``.blf``, ``.csv``, ``.trc`` and ``.gz``
  compressed variants, and ``.mf4`` (ASAM MDF 4 through asammdf, the contract's DBC
  attached to the file): only the suffixes `hil.logio` reads back
  (`hil.logio.check_log_suffix`). An MF4 is written whole when the recording stops.
  Every frame is marked with its direction from the ECU's point of view, as a logger on
  the ECU's own interface would mark it: the frames the ECU transmits per the DBC
  (`transmitted_ids`: HIL_SYNC_ACK, STEER_TORQUE_CMD, CTRL_DIAG) are Tx
  (``is_rx = False``), every other frame Rx. The recorder's own bus object hears every
  frame as received, so the direction is set here; candump, ASC, BLF, TRC and MF4 carry
  it, CSV and SQLite do not. The project's readers find the ECU's frames by ID, never by
  direction, so logs recorded before (every frame Rx) read the same.
  In lockstep (``virtual_time=True``) every frame is stamped with the wall-clock start
  of the recording plus the virtual time of the tick it belongs to
  (`hil.logio.TickStamper`), so ``cantools plot``, ``can.player``, ``canplayer`` and
  ``hil play`` see the drive at its true speed, not at the speed the PC computed it;
  the wall clock of the first and last frame is kept in `wall_start` / `wall_end` for
  the sidecar. Real-time recordings keep the bus timestamps (wall clock).
- `EcuFrameMonitor`: a node for the time master that keeps the ECU's frames with the
  virtual tick they answered (STEER_TORQUE_CMD, CTRL_DIAG), for time series and metrics.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Iterable

import can
import numpy as np

from can_defs.codec import decode
from can_defs.dbc import DBC_PATH, load_database
from can_defs.errors import CanDefsError
from can_defs.frames import CtrlDiag, FrameId, SteerTorqueCmd
from can_defs.log_reader import is_contract_data_frame
from hil.errors import HilError
from hil.logio import TickStamper, check_log_suffix

#: Default log format: candump ``-L`` lines (``(timestamp) channel ID#DATA``).
DEFAULT_LOG_SUFFIX = ".log"

#: Columns of the ECU frame time series (one row per control cycle).
ECU_TRACE_COLUMNS = ("time", "ctrl_mode", "cmd_valid", "steer_angle_cmd", "drive_torque_cmd",
                     "qp_status", "solve_time_us", "cycle_time_us", "qp_iter", "overruns",
                     "faults")


#: The node from whose point of view logs mark direction: the device under test.
DEVICE_UNDER_TEST = "ECU"


def transmitted_ids(node: str = DEVICE_UNDER_TEST) -> frozenset[int]:
    """IDs of the frames ``node`` transmits per the contract's DBC (its transmitter node;
    for the ECU: HIL_SYNC_ACK, STEER_TORQUE_CMD and CTRL_DIAG)."""
    return frozenset(message.frame_id for message in load_database().messages
                     if node in message.senders)


class RecorderError(HilError):
    """The log file cannot be written (unknown suffix, unwritable folder)."""


class BusRecorder:
    """Every frame on the bus to ``path`` (format by suffix), until `stop`.

    Args:
        bus: a bus object of its own (the recorder closes it on `stop`).
        path: the log file; its folder must exist (checked by the commands beforehand).
        virtual_time: stamp frames with the wall-clock start + their lockstep tick
            (module docstring) instead of the bus timestamps.
        tx_ids: IDs of the data frames marked transmitted (Tx); default the ECU's
            (`transmitted_ids`). Every other frame is marked received (Rx).

    Raises:
        RecorderError: a suffix the project's log readers do not read, or the file cannot
            be created.
    """

    def __init__(self, bus: can.BusABC, path: str | Path, virtual_time: bool = False,
                 tx_ids: Iterable[int] | None = None) -> None:
        self.path = Path(path)
        self.bus = bus
        self.count = 0
        self._tx_ids = frozenset(transmitted_ids() if tx_ids is None else tx_ids)
        #: Wall clock (Unix time, s) of the first and the last frame received.
        self.wall_start: float | None = None
        self.wall_end: float | None = None
        self._stamper = TickStamper() if virtual_time else None
        try:
            suffix = check_log_suffix(self.path)
            # an MF4 carries its DBC, so tools decode its signals without looking for it
            options = {"database": DBC_PATH} if suffix == ".mf4" else {}
            self._writer = can.Logger(self.path, **options)
            # binary formats keep the channel as a small integer (MF4 one byte, BLF two)
            self._integer_channel = suffix in (".mf4", ".blf")
        except (HilError, ValueError, OSError, NotImplementedError) as e:  # MF4 without asammdf
            bus.shutdown()
            raise RecorderError(f"cannot record to {self.path}: {e}") from e
        self._notifier = can.Notifier(bus, [self._receive], timeout=0.05)
        self._stopped = False

    def _receive(self, message: can.Message) -> None:
        """Notifier callback (its thread): count, mark the direction, then write now or
        once the tick is known."""
        self.count += 1
        # every bus object gets its own copy of a frame: marking it changes nobody else's
        message.is_rx = not (is_contract_data_frame(message)
                             and message.arbitration_id in self._tx_ids)
        if self._integer_channel and not 0 <= (can.util.channel2int(message.channel) or 0) <= 255:
            # MF4 and BLF keep the bus channel as a small integer, taken from the name's
            # trailing digits (python-can): a name such as 'hil-...8454' would fail the write
            # and lose the frame, so such a channel is recorded as unknown
            message.channel = None
        if self.wall_start is None:
            self.wall_start = message.timestamp
        self.wall_end = message.timestamp
        if self._stamper is None:
            self._writer.on_message_received(message)
            return
        self._write_stamped(self._stamper.push(message))

    def _write_stamped(self, ready: list[tuple[can.Message, int]]) -> None:
        start = self.wall_start if self.wall_start is not None else 0.0
        for message, tick_ms in ready:
            message.timestamp = start + tick_ms / 1000.0
            self._writer.on_message_received(message)

    def wait_for(self, n_frames: int, timeout_s: float = 5.0) -> bool:
        """Wait until ``n_frames`` frames were recorded (the frames are in flight on the
        receive thread when the run ends); True if reached within ``timeout_s``."""
        give_up = time.monotonic() + timeout_s
        while self.count < n_frames and time.monotonic() < give_up:
            time.sleep(0.005)
        return self.count >= n_frames

    def stop(self, settle_s: float = 0.1, max_wait_s: float = 1.0) -> None:
        """Stop listening once the bus has been quiet for ``settle_s`` (frames sent just
        before, e.g. the ECU's last command on shutdown, are still recorded; at most
        ``max_wait_s``), then flush and close the log and the bus object (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        give_up = time.monotonic() + max_wait_s
        seen = -1
        while self.count != seen and time.monotonic() < give_up:
            seen = self.count
            time.sleep(settle_s)
        try:
            self._notifier.stop()
            if self._stamper is not None:
                # frames after the last HIL_SYNC (an interrupted run): the last tick
                self._write_stamped(self._stamper.flush())
        finally:
            try:
                self._writer.stop()  # flush and close the log
            finally:
                self.bus.shutdown()

    def __enter__(self) -> "BusRecorder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class EcuFrameMonitor:
    """Time-master node that keeps the ECU's command and diagnosis frames per tick.

    It checks nothing (the plant has its own E2E receiver); frames that do not decode are
    counted in `undecodable`.
    """

    def __init__(self) -> None:
        self.commands: list[tuple[int, SteerTorqueCmd]] = []
        self.diags: list[tuple[int, CtrlDiag]] = []
        self.raw: list[tuple[int, int, bytes]] = []
        self.undecodable = 0

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        """The monitor sends nothing."""
        return []

    def receive(self, message: can.Message, tick_ms: int) -> None:
        """Keep STEER_TORQUE_CMD and CTRL_DIAG with the tick they were received in."""
        if message.arbitration_id not in (FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG):
            return
        data = bytes(message.data)
        self.raw.append((tick_ms, message.arbitration_id, data))
        try:
            frame = decode(message.arbitration_id, data).frame
        except CanDefsError:
            self.undecodable += 1
            return
        if isinstance(frame, SteerTorqueCmd):
            self.commands.append((tick_ms, frame))
        else:
            self.diags.append((tick_ms, frame))

    def advance(self, tick_ms: int, dt_s: float) -> None:
        """No dynamics."""

    def trace(self) -> dict[str, np.ndarray]:
        """One row per control cycle: column -> array (n_cycles,) (columns
        :data:`ECU_TRACE_COLUMNS`; time = the tick of the command's reception, s).

        The ECU sends STEER_TORQUE_CMD then CTRL_DIAG each cycle, so the i-th of each
        belong together (in real time the two may be received in different ticks); the
        extra CMD_VALID = 0 command the ECU sends when it stops has no diagnosis and is
        left out.
        """
        rows = []
        for (tick, cmd), (_, diag) in zip(self.commands, self.diags):
            rows.append((tick / 1000.0, int(cmd.ctrl_mode), float(cmd.cmd_valid),
                         cmd.steer_angle_cmd, cmd.drive_torque_cmd, int(diag.qp_status),
                         diag.solve_time_us, diag.cycle_time_us, diag.qp_iter, diag.overruns,
                         diag.faults))
        table = np.array(rows, dtype=float).reshape(-1, len(ECU_TRACE_COLUMNS))
        return {name: table[:, i].copy() for i, name in enumerate(ECU_TRACE_COLUMNS)}

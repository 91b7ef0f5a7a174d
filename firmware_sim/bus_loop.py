"""The ECU's loop on its bus: receive with a short timeout, hand each frame to the node, a
lost bus noticed and reopened, and the last frame and shutdown when the node closes.

``BusLoop`` is a part of ``firmware_sim.ecu.Ecu`` (a base class of it): ``run`` (the
blocking loop), the lost-bus state (the end of the interface's stream, or receive errors
for 100 ms: logged at most once a second, reopened every second, real-time tasks go on)
and ``close``. It uses the node's bus, transmitter and schedule that ``Ecu.__init__`` sets
up, and the node's ``handle_message`` and ``poll``.
"""
from __future__ import annotations

import logging
import select
import socket
import threading
import time

import can
from can_defs.frames import CtrlMode

from firmware_sim.clock import clock_ns
from firmware_sim.config import BUS_LOST_AFTER_MS, BUS_REOPEN_INTERVAL_S

#: The ECU's logger: its lines keep the name ``firmware_sim.ecu`` whichever part logs them.
_LOG = logging.getLogger("firmware_sim.ecu")

#: Wait of one `bus.recv` in `run`, s: bounds the reaction to ``stop_event``.
RECV_TIMEOUT_S = 0.05


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


class BusLoop:
    """The bus loop of ``firmware_sim.ecu.Ecu`` (see the module docstring)."""

    def _recv_timeout(self) -> float:
        if self.lockstep:
            return RECV_TIMEOUT_S
        return min(RECV_TIMEOUT_S, self._seconds_until_release(clock_ns(self._clock)))

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
            wait = min(wait, self._seconds_until_release(clock_ns(self._clock)))
        stop_event.wait(max(wait, 0.001))

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

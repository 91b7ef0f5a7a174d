"""The contract's lost-bus rule whatever python-can's interface does underneath (issue 38,
item 4): rate-limited reopening and one warning per episode are the ECU's (``Ecu.run``),
so the interface itself must neither spin nor flood the log.

python-can's ``socketcand`` interface (4.x) connects in a loop without a pause for 10 s,
logging a warning per attempt: about 32,000 lines a second while the server is down, and a
start-up that blocks 10 s. `quiet_socketcand` replaces that loop with one connection
attempt with a timeout (the ECU retries every second), and `RateLimitFilter` keeps any
interface module's own log lines to one a second per kind, with the count of the rest.
"""
from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable

#: Seconds one connection attempt to a socketcand server may take.
CONNECT_TIMEOUT_S = 2.0
#: The python-can loggers whose lines are rate limited.
INTERFACE_LOGGERS = ("can.interfaces.socketcand.socketcand", "can.interfaces.socketcand")


class RateLimitFilter(logging.Filter):
    """At most one record a second per (logger, level, first words of the message); the
    next record let through says how many were dropped."""

    def __init__(self, interval_s: float = 1.0, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self._interval_s = interval_s
        self._clock = clock
        self._last: dict[tuple[str, int, str], float] = {}
        self._dropped: dict[tuple[str, int, str], int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.levelno, record.getMessage()[:32])
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self._interval_s:
            self._dropped[key] = self._dropped.get(key, 0) + 1
            return False
        self._last[key] = now
        dropped = self._dropped.pop(key, 0)
        if dropped:
            record.msg = f"{record.getMessage()} ({dropped} more like this in the last {now - last:.0f} s)"
            record.args = None
        return True


def connect_once(sock: socket.socket, host: str, port: int) -> None:
    """One connection attempt with a timeout, in place of python-can's 10 s loop.

    Raises:
        ConnectionError: no server answered (an OSError: the bus opener's error line).
    """
    sock.settimeout(CONNECT_TIMEOUT_S)
    try:
        sock.connect((host, port))
    except OSError as error:
        raise ConnectionError(f"no socketcand server at {host}:{port}: "
                              f"{error.strerror or error}") from None
    finally:
        sock.settimeout(None)


_FILTER = RateLimitFilter()


def quiet_socketcand() -> None:
    """Install `connect_once` in python-can's socketcand interface and the rate limit on
    the interface's loggers (idempotent; an interface without that function is left as it is)."""
    for name in INTERFACE_LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
    try:
        from can.interfaces.socketcand import socketcand as module
    except ImportError:
        return
    if hasattr(module, "connect_to_server"):
        module.connect_to_server = connect_once

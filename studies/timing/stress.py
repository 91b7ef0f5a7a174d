"""CPU stress for the timing benchmark: one busy-looping process per core.

Each load process runs pure-Python arithmetic in an endless loop at normal priority
(SCHED_OTHER, nice 0), pinned to its core, so that it competes for exactly that core the
whole time: under the Linux CFS scheduler a process of normal priority in the benchmark
(or any other job) then gets about half of its core; a SCHED_FIFO process preempts the
load at once.
"""
from __future__ import annotations

import os
import subprocess
import sys

from firmware_sim.timing import apply_realtime_policy

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """``preexec_fn`` for the benchmark's child processes: SIGTERM when the parent dies.

    Without it a benchmark killed with SIGKILL would leave busy loops running, or an ECU
    under SCHED_FIFO whose bus peer is gone. Linux only; elsewhere a no-op.
    """
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        pass

#: What each load process runs: integer arithmetic forever, no system calls.
BUSY_LOOP = "x = 0\nwhile True:\n    x = (x * 1103515245 + 12345) & 0xFFFFFFFF\n"


class StressLoad:
    """Busy-loop processes, one pinned to each of ``cpus``; a context manager.

    ``cpus`` empty means no load (the "idle" condition), so callers need no branch.
    """

    def __init__(self, cpus: tuple[int, ...]) -> None:
        self.cpus = cpus
        self._processes: list[subprocess.Popen[bytes]] = []
        self.pinned: list[str] = []

    def start(self) -> "StressLoad":
        """Start the load processes."""
        for cpu in self.cpus:
            process = subprocess.Popen([sys.executable, "-c", BUSY_LOOP],
                                       stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
            self._processes.append(process)
            policy = apply_realtime_policy(cpu if cpu < (os.cpu_count() or 1) else None,
                                           None, pid=process.pid)
            self.pinned.append(policy.describe())
        return self

    def stop(self) -> None:
        """Terminate (then kill) every load process (idempotent)."""
        for process in self._processes:
            if process.poll() is None:
                process.terminate()
        for process in self._processes:
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        self._processes.clear()

    def __enter__(self) -> "StressLoad":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

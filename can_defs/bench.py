"""Per-frame cost of the codec and the E2E receiver (the ECU calls them ~200 times/s).

Usage: ``python -m can_defs.bench [--repeat N]``. Prints microseconds per call (median of
five runs of N calls each); a report, never a pass/fail threshold.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

from can_defs.codec import FrameSender, decode, encode
from can_defs.e2e import E2EMonitor
from can_defs.frames import CtrlMode, FrameId, SteerTorqueCmd, VehDyn


def _microseconds_per_call(function: Callable[[], object], repeat: int) -> float:
    runs = []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeat):
            function()
        runs.append((time.perf_counter() - start) / repeat * 1e6)
    return statistics.median(runs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m can_defs.bench", description=__doc__)
    parser.add_argument("--repeat", type=int, default=2000, help="calls per timed run")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        print(f"error: --repeat must be >= 1, got {args.repeat}", file=sys.stderr)
        return 2
    command = SteerTorqueCmd(CtrlMode.ACTIVE, True, 0.12, -350.4)
    dynamics = VehDyn(13.9, -0.21, 0.05)
    payload = encode(dynamics, 3)
    sender = FrameSender()
    monitor = E2EMonitor()
    counter = iter(range(10**9))
    frames = [encode(dynamics, c % 16) for c in range(16)]
    cases = {
        "encode(SteerTorqueCmd)": lambda: encode(command, 5),
        "FrameSender.encode(VehDyn)": lambda: sender.encode(dynamics),
        "decode(VEH_DYN)": lambda: decode(FrameId.VEH_DYN, payload),
        "E2EMonitor.check(VEH_DYN)": lambda: monitor.check(FrameId.VEH_DYN, frames[next(counter) % 16]),
    }
    print(f"python {sys.version.split()[0]}, {args.repeat} calls x 5 runs, median")
    for name, function in cases.items():
        print(f"{name:<28} {_microseconds_per_call(function, args.repeat):7.1f} us/call")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

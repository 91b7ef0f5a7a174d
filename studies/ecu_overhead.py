"""Measure the ECU's own cost, without a control law: ``python -m studies.ecu_overhead``.

Runs the ECU with `ScriptedController` (a one-line law) on a private python-can virtual
bus, fed by peer nodes in the same process:

- lockstep: ``--cycles`` control cycles (5 ticks each); wall time of every control task
  (mode logic, law, guard, encode, TX of 2 frames) and of every tick (all frames of the
  tick handled, up to the HIL_SYNC_ACK sent);
- real time: ``--seconds`` of `Ecu.run` on ``time.monotonic`` with a feeder thread that
  sends the plant frames every 10 ms and PLANNER_REQ every 25 ms on absolute deadlines;
  release jitter, task time, input age and RX-to-TX latency from the ECU's timing record.

Writes a JSON summary (seconds; p50 / p99 / p99.9 / max) to ``--out`` and prints it.
Figures depend on the machine and its load: they are measurements, not requirements.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

from firmware_sim.ecu import Ecu
from hil.ecu_harness import PeerNodes, ScriptedController, pump
from firmware_sim.timing import PERCENTILES


def _stats(values_s: np.ndarray) -> dict[str, float]:
    values_s = values_s[np.isfinite(values_s)]
    stats = {"n": int(values_s.size)}
    for q in PERCENTILES:
        stats[f"p{q:g}"] = float(np.percentile(values_s, q))
    stats["max"] = float(values_s.max())
    return stats


def measure_lockstep(cycles: int) -> dict[str, object]:
    """Lockstep: per-tick wall time (SYNC handled -> ACK sent) and per control task time."""
    channel = f"overhead-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel) as ecu_bus, \
            can.Bus(interface="virtual", channel=channel) as peer_bus:
        ecu = Ecu(ecu_bus, "scripted", {1: Path("straight")}, lockstep=True,
                  controller_factory=lambda name: ScriptedController(solve_time_s=0.0),
                  path_loader=str)
        peers = PeerNodes(peer_bus)
        peers.send_handshake()
        pump(ecu, ecu_bus)
        tick_times = np.empty(cycles * 5)
        for index, t in enumerate(range(0, cycles * 25, 5)):
            if t % 10 == 0:
                peers.send_plant(vx=10.0, x=t * 0.01)
            if t % 25 == 0:
                peers.send_planner()
            peers.send_sync(t)
            started = time.perf_counter()
            pump(ecu, ecu_bus)
            tick_times[index] = time.perf_counter() - started
            peers.received()
        ecu.close()
        return {"control_cycles": cycles, "final_mode": ecu.mode.name,
                "tick_wall_time_s": _stats(tick_times),
                "control_task_time_s": _stats(ecu.timing.column("task_time"))}


def measure_realtime(seconds: float) -> dict[str, object]:
    """Real time: the ECU's timing record over ``seconds`` of `Ecu.run`."""
    channel = f"overhead-rt-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel) as ecu_bus, \
            can.Bus(interface="virtual", channel=channel) as peer_bus:
        ecu = Ecu(ecu_bus, "scripted", {1: Path("straight")}, lockstep=False,
                  controller_factory=lambda name: ScriptedController(solve_time_s=0.0),
                  path_loader=str)
        peers = PeerNodes(peer_bus)
        stop = threading.Event()

        def feeder() -> None:
            # 5 ms base tick on absolute deadlines: plant every 10 ms, planner every 25 ms
            next_release = time.monotonic()
            k = 0
            while not stop.is_set():
                if k % 2 == 0:
                    peers.send_plant(vx=10.0, x=0.05 * k)
                if k % 5 == 0:
                    peers.send_planner()
                k += 1
                next_release += 0.005
                stop.wait(max(0.0, next_release - time.monotonic()))

        feeder_thread = threading.Thread(target=feeder)
        ecu_thread = threading.Thread(target=ecu.run, args=(stop,))
        feeder_thread.start()
        ecu_thread.start()
        time.sleep(seconds)
        stop.set()
        feeder_thread.join()
        ecu_thread.join()
        ecu.close()
        summary = ecu.timing.summary()
        return {"seconds": seconds, "control_cycles": ecu.timing.count,
                "overruns": ecu.overruns, "final_mode": ecu.mode.name, "timing_s": summary}


def main(argv: list[str] | None = None) -> int:
    """Run both measurements and write the JSON summary."""
    parser = argparse.ArgumentParser(prog="python -m studies.ecu_overhead", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=2000, help="lockstep control cycles")
    parser.add_argument("--seconds", type=float, default=5.0, help="real-time run length, s")
    parser.add_argument("--out", type=Path, default=Path("results/ecu_overhead.json"))
    args = parser.parse_args(argv)
    if args.cycles <= 0 or args.seconds <= 0:
        print("error: --cycles and --seconds must be positive", file=sys.stderr)
        return 2
    result = {"machine": platform.platform(), "python": platform.python_version(),
              "lockstep": measure_lockstep(args.cycles),
              "realtime": measure_realtime(args.seconds)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

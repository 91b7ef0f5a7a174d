"""The plant process of the timing benchmark: plant, planner and a command audit on the
wall clock, on a socketcand bus (see `hil.timing.hub`), pinned to one core.

    python -m hil.timing.plant_side --port P --scenario FILE.toml --out RESULT.json \
        [--cpu 1] [--rt-priority 40]

It runs `hil.time_master.RealTimeMaster` (5 ms ticks on absolute deadlines) for the
scenario's duration and writes a JSON result: the master's tick statistics, the command
audit (every STEER_TORQUE_CMD through an E2E receiver: lost, repeated, CRC errors, arrival
times on CLOCK_MONOTONIC, which the ECU's timing record shares), the plant's rejected
commands and the tracking error on the true pose.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import can  # noqa: E402
import numpy as np  # noqa: E402

from can_defs.codec import decode  # noqa: E402
from can_defs.e2e import E2EReceiver, E2EStatus  # noqa: E402
from can_defs.errors import CanDefsError  # noqa: E402
from can_defs.frames import FrameId  # noqa: E402
from firmware_sim.timing import apply_realtime_policy  # noqa: E402
from hil.errors import HilError  # noqa: E402

#: The socketcand channel name every process of the benchmark opens on the hub.
CHANNEL = "vcan0"


class CommandAudit:
    """Time-master node that checks every STEER_TORQUE_CMD as the plant's receiver would
    and stamps its arrival on ``clock`` (CLOCK_MONOTONIC by default)."""

    def __init__(self, clock: Any = time.monotonic) -> None:
        self._clock = clock
        self._receiver = E2EReceiver(FrameId.STEER_TORQUE_CMD)
        self.arrivals: list[float] = []
        self.modes: list[int] = []

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        """The audit sends nothing."""
        return []

    def receive(self, message: can.Message, tick_ms: int) -> None:
        """Check and stamp one STEER_TORQUE_CMD; other frames are ignored."""
        if message.arbitration_id != FrameId.STEER_TORQUE_CMD or message.is_extended_id:
            return
        now = self._clock()
        data = bytes(message.data)
        self._receiver.check(data)
        try:
            mode = int(decode(message.arbitration_id, data).frame.ctrl_mode)
        except CanDefsError:
            mode = -1
        self.arrivals.append(now)
        self.modes.append(mode)

    def advance(self, tick_ms: int, dt_s: float) -> None:
        """No dynamics."""

    def result(self) -> dict[str, Any]:
        """Counts per E2E status, frames lost (alive-counter gaps), arrival times (s)."""
        stats = self._receiver.stats
        counts = {status.name: int(stats.counts[status]) for status in E2EStatus}
        return {"received": len(self.arrivals), "lost": int(stats.lost),
                "e2e_errors": int(stats.e2e_errors), "status_counts": counts,
                "arrivals": self.arrivals, "modes": self.modes}


def run_plant_side(port: int, scenario_file: Path) -> dict[str, Any]:
    """Run the plant, planner and audit for the scenario's duration on the hub at ``port``
    (``hil.rig.Rig`` in real time; the ECU is another process, started by the benchmark);
    the JSON-ready result."""
    from hil.bus import BusConfig
    from hil.rig import NoEcu, Rig, RigHooks
    from hil.run_types import RunOptions
    from hil.scenario import load_scenario

    scenario = load_scenario(scenario_file)
    audit = CommandAudit()
    times: dict[str, float] = {}

    def before_run() -> None:
        time.sleep(0.2)  # the hub delivers to a new client after its READY_DELAY_S
        # Python's full (generation 2) collection scans every tracked object, the loaded
        # modules, numpy and python-can included: measured 23-44 ms once in every run,
        # about 70 s (120 s runs) into the plant's loop, which held the plant's ticks and
        # the commands it stamps (the "plant stall" of the timing runs). Frozen, the
        # objects of start-up are left out of every later collection.
        gc.collect()
        gc.freeze()
        times["started"] = time.monotonic()

    options = RunOptions(controller="(another process)", bus=BusConfig("socketcand", CHANNEL), lockstep=False)
    rig = Rig(scenario, options, RigHooks(ecu=lambda rig: NoEcu(), nodes=[audit], before_run=before_run,
                                          bus_options={"host": "127.0.0.1", "port": port, "tcp_tune": True}))
    with rig:
        stats = rig.run()
        ended = time.monotonic()
    result = rig.result()
    trace = result.plant_trace
    return {"started": times["started"], "ended": ended, "ticks": stats.ticks,
            "tick_overruns": stats.overruns, "tick_max_lateness_s": stats.max_lateness_s,
            "frames_sent": stats.frames_sent, "frames_received": stats.frames_received,
            "plant_commands_rejected": rig.plant.commands_rejected,
            "commands": audit.result(),
            "tracking": result.tracking.as_dict(),
            "final_vx": float(trace["vx"][-1]) if len(trace["vx"]) else float("nan")}


def main(argv: list[str] | None = None) -> int:
    """Command line; prints ``error: ...`` and exits 1 on failure."""
    parser = argparse.ArgumentParser(prog="python -m hil.timing.plant_side",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, required=True, help="hub port on 127.0.0.1")
    parser.add_argument("--scenario", type=Path, required=True, help="scenario TOML file")
    parser.add_argument("--out", type=Path, required=True, help="result JSON file")
    parser.add_argument("--cpu", type=int, default=None, help="pin to this CPU")
    parser.add_argument("--rt-priority", type=int, default=None, help="SCHED_FIFO priority")
    args = parser.parse_args(argv)
    try:
        policy = apply_realtime_policy(args.cpu, args.rt_priority)
        result = run_plant_side(args.port, args.scenario)
    except (HilError, can.CanError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result["scheduling"] = policy.describe()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, default=_json_default) + "\n")
    return 0


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {value!r}")


if __name__ == "__main__":
    sys.exit(main())

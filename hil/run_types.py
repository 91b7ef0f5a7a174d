"""What one HIL run takes and gives: :class:`RunOptions` (the controller, the bus, the
time base, the ECU of either kind, faults, logging) and :class:`HilRunResult` (the plant's
true time series, the ECU's frames per control cycle, the tracking metrics, the run facts),
with the constants of the run's ECU (where the C ECU is, which controllers it has).

``hil.rig`` builds a run from the options; ``hil.session.run_hil`` is the one-call form.
"""
from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from can_defs.frames import CtrlMode
from hil.bus import BusConfig, private_virtual_channel
from hil.errors import HilError
from hil.metrics import TrackingMetrics
from hil.planner_node import engage_from_start
from hil.time_master import DEFAULT_ACK_TIMEOUT_S, DEFAULT_HANDSHAKE_TIMEOUT_S, MasterStats

#: Wall-clock wait for a stopped ECU process before it is killed.
ECU_STOP_TIMEOUT_S = 5.0
#: Root of the checkout (the ECU process runs from here).
REPO_ROOT = Path(__file__).resolve().parent.parent
#: The C ECU executable (``make firmware``), for ``RunOptions.ecu`` "c".
C_ECU_EXECUTABLE = REPO_ROOT / "build" / "firmware" / "ecu"
#: ECU implementations a run can use: firmware_sim (Python) and the C executable.
ECU_IMPLEMENTATIONS = ("python", "c")
#: Controllers the C ECU has (firmware_sim.native.NATIVE_CONTROLLERS).
C_ECU_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: Channel name on a run's own socketcand hub (the hub routes by channel name only).
HUB_CHANNEL = "vcan0"



class SessionError(HilError):
    """The HIL run could not be set up or its ECU failed."""


@dataclass(frozen=True)
class RunOptions:
    """How to run one scenario over CAN.

    ``lockstep`` False runs on the wall clock. ``log_path`` None records nothing.
    ``engage`` overrides the planner's engage schedule (virtual time s -> bool).
    ``ecu_output`` is where a separate ECU process writes stdout/stderr (default: a
    temporary file, shown in errors). ``faults`` (a ``hil.faults.FaultSpec``) puts a
    fault injector between the HIL nodes and the bus and changes the plant; what it did
    is in ``HilRunResult.extra["injector"]`` (its ``records()``).
    """

    controller: str
    bus: BusConfig
    lockstep: bool = True
    log_path: Path | None = None
    handshake_timeout_s: float = DEFAULT_HANDSHAKE_TIMEOUT_S
    ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S
    engage: Callable[[float], bool] = engage_from_start
    ecu_output: Path | None = None
    ecu_extra_args: tuple[str, ...] = ()
    #: Faults to inject (``hil.faults.FaultSpec``); None injects nothing.
    faults: Any = None
    #: Builds the in-process ECU's controller from its name (``firmware_sim.ecu.Ecu``'s
    #: ``controller_factory``; e.g. another model artefact); None: the registry. Only on
    #: the virtual bus: a separate ECU process builds its own.
    controller_factory: Callable[[str], Any] | None = None
    #: The ECU's ``--model`` (another model file) and ``--excite`` (identification
    #: excitation program), passed to the in-process ECU or to the ECU process alike.
    model: Path | None = None
    excite: str | None = None
    #: Which ECU: "python" (firmware_sim) or "c" (the executable ``C_ECU_EXECUTABLE``, a
    #: process; on the virtual interface the run uses a loopback socketcand hub).
    ecu: str = "python"


@dataclass
class HilRunResult:
    """Outcome of one run: time series (column -> array (n,)), metrics, run facts."""

    scenario: str
    controller: str
    bus: str
    mode: str
    plant_trace: dict[str, np.ndarray]
    ecu_trace: dict[str, np.ndarray]
    tracking: TrackingMetrics
    stats: MasterStats
    wall_time_s: float
    log_path: Path | None = None
    frames_logged: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-ready facts and metrics of the run."""
        ecu = self.ecu_trace
        solve_us = ecu["solve_time_us"][ecu["qp_status"] != 15] if len(ecu["time"]) else []
        active = ecu["ctrl_mode"] == int(CtrlMode.ACTIVE) if len(ecu["time"]) else []
        return {
            "scenario": self.scenario, "controller": self.controller, "bus": self.bus,
            "mode": self.mode, "wall_time_s": round(self.wall_time_s, 3),
            "ticks": self.stats.ticks, "frames_sent": self.stats.frames_sent,
            "frames_received": self.stats.frames_received,
            "realtime_overruns": self.stats.overruns,
            "control_cycles": int(len(ecu["time"])),
            "active_cycles": int(np.sum(active)),
            "solve_time_us_median": float(np.median(solve_us)) if len(solve_us) else None,
            "solve_time_us_max": float(np.max(solve_us)) if len(solve_us) else None,
            "log": str(self.log_path) if self.log_path else None,
            "frames_logged": self.frames_logged,
            "tracking": self.tracking.as_dict(),
        }

    def write(self, out_dir: Path) -> list[Path]:
        """Write ``plant.csv``, ``ecu.csv`` and ``summary.json`` to ``out_dir`` (its parent
        must exist: no folder tree is created silently)."""
        out_dir.mkdir(exist_ok=True)
        written = [_write_csv(out_dir / "plant.csv", self.plant_trace),
                   _write_csv(out_dir / "ecu.csv", self.ecu_trace)]
        summary = out_dir / "summary.json"
        summary.write_text(json.dumps(self.summary(), indent=2) + "\n", encoding="utf-8")
        written.append(summary)
        return written


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    names = list(columns)
    with path.open("w", newline="", encoding="ascii") as handle:
        writer = csv.writer(handle)
        writer.writerow(names)
        for row in zip(*(columns[n] for n in names)):
            writer.writerow([f"{v:.9g}" for v in row])
    return path


def default_options(controller: str, bus: BusConfig | None = None, **kwargs: Any) -> RunOptions:
    """Options for a run on a private virtual channel (tests, ``make run``)."""
    bus = bus or BusConfig("virtual", private_virtual_channel())
    return RunOptions(controller=controller, bus=bus, **kwargs)

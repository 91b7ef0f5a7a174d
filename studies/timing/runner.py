"""One timing run: the ECU and the plant as separate processes on separate cores.

Processes (all on 127.0.0.1, CLOCK_MONOTONIC shared):

- the bus: `hil.timing.hub` (socketcand protocol over TCP loopback), on the plant's core,
  SCHED_FIFO ``hub_priority`` (above the plant, so a frame is forwarded at once);
- the ECU: ``python -m firmware_sim --interface socketcand --realtime --cpu ECU_CPU
  --rt-priority P --timing-out FILE.npz`` (its own CLI), started first; the run waits for
  its ``ready:`` line (controller and path loaded); with ``ecu="c"`` the C ECU executable
  (``build/firmware/ecu``, ``make firmware``; issue 18) with the same options, which writes
  the same record;
- the plant: `hil.timing.plant_side` on ``plant_cpu``, SCHED_FIFO ``plant_priority``, for
  the scenario's duration (35 km/h, mu 0.85, repeated double lane changes).

Then the ECU is stopped with SIGTERM and writes its per-cycle timing record.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_sim.timing import TimingRecord, apply_realtime_policy, load_timing
from hil.errors import HilError
from studies.timing.paths import write_repeated_lane_change
from hil.timing.plant_side import CHANNEL
from studies.timing.stress import die_with_parent

REPO_ROOT = Path(__file__).resolve().parents[2]
#: The C ECU executable (make firmware).
C_ECU_EXECUTABLE = REPO_ROOT / "build" / "firmware" / "ecu"
SPEED_KMH = 35.0
ECU_READY_TIMEOUT_S = 120.0
_STOP_TIMEOUT_S = 10.0


class TimingRunError(HilError):
    """A process of the timing run failed to start or ended with an error."""


@dataclass(frozen=True)
class Placement:
    """Cores and SCHED_FIFO priorities (None: normal scheduling) of the run's processes."""

    ecu_cpu: int | None = 0
    plant_cpu: int | None = 1
    ecu_priority: int | None = 50
    hub_priority: int | None = 45
    plant_priority: int | None = 40

    @classmethod
    def for_this_machine(cls, fifo: bool = True) -> "Placement":
        """ECU on CPU 0 and plant on CPU 1 where there are two CPUs, else no pinning."""
        two = len(os.sched_getaffinity(0)) >= 2
        cpus = sorted(os.sched_getaffinity(0))
        return cls(ecu_cpu=cpus[0] if two else None, plant_cpu=cpus[1] if two else None,
                   ecu_priority=50 if fifo else None, hub_priority=45 if fifo else None,
                   plant_priority=40 if fifo else None)


@dataclass
class TimingRun:
    """Outcome of one run: the ECU's record, the plant side's result and how each
    process was scheduled. ``controller`` is the row's label: "NAME (C)" for the C ECU;
    ``release`` the ECU's ``--release`` (clock or sample)."""

    controller: str
    seconds: float
    ecu: TimingRecord
    plant: dict[str, Any]
    scheduling: dict[str, str]
    ecu_log: str
    release: str = "clock"


def cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs from /proc/stat, None where unreadable.

    Steal is time the hypervisor ran something else while this (virtual) machine had work:
    a guest's SCHED_FIFO cannot protect against it.
    """
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    values = [int(v) for v in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return values[7], sum(values)


def steal_share(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float:
    """Share of CPU time stolen by the hypervisor between two `cpu_times` (NaN if unknown)."""
    if before is None or after is None or after[1] <= before[1]:
        return float("nan")
    return (after[0] - before[0]) / (after[1] - before[1])


def _env(port: int) -> dict[str, str]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               CAN_CONFIG=json.dumps({"host": "127.0.0.1", "port": port, "tcp_tune": True}))
    env.pop("CAN_INTERFACE", None)
    env.pop("CAN_CHANNEL", None)
    return env


def write_scenario(work_dir: Path, seconds: float) -> Path:
    """Scenario TOML (and its path CSV) for ``seconds`` at 35 km/h on high mu."""
    path_file = write_repeated_lane_change(work_dir / "path.csv",
                                           SPEED_KMH / 3.6 * seconds + 100.0)
    scenario = work_dir / "scenario.toml"
    scenario.write_text(
        'name = "timing"\n'
        'description = "timing benchmark: repeated double lane changes, 35 km/h, mu 0.85"\n'
        f"duration_s = {seconds!r}\n\n"
        f'[path]\nid = 1\nfile = "{path_file.name}"\n\n[road]\nmu = 0.85\n\n'
        "[vehicle]\nmass_offset_kg = 0.0\n\n"
        f"[start]\nx_m = 0.0\ny_m = 0.0\nyaw_rad = 0.0\nspeed_kmh = {SPEED_KMH}\n\n"
        f"[speed_profile]\ntime_s = [0.0]\ntarget_speed_kmh = [{SPEED_KMH}]\n")
    return scenario


def _stop(process: subprocess.Popen[Any], timeout_s: float = _STOP_TIMEOUT_S) -> int:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def ecu_label(controller: str, ecu: str = "python") -> str:
    """A run's name in the tables: the controller, "NAME (C)" on the C ECU."""
    return f"{controller} (C)" if ecu == "c" else controller


def run_timing(controller: str, seconds: float, work_dir: Path,
               placement: Placement | None = None, ecu: str = "python",
               release: str = "clock") -> TimingRun:
    """Run the ECU with ``controller`` against the plant for ``seconds`` (see module doc);
    ``ecu`` "python" (firmware_sim) or "c" (the executable ``C_ECU_EXECUTABLE``);
    ``release``: the ECUs' ``--release`` (clock: contract revision 2; sample: revision 3).

    Raises:
        TimingRunError: the C ECU is not built; the hub, the ECU or the plant process
            failed (with its output).
    """
    label = ecu_label(controller, ecu)
    c_ecu = ecu == "c"  # (the name ecu is the process below)
    if c_ecu and not C_ECU_EXECUTABLE.is_file():
        raise TimingRunError(f"the C ECU {C_ECU_EXECUTABLE} is not built: run make firmware")
    placement = placement or Placement.for_this_machine()
    work_dir.mkdir(parents=True, exist_ok=True)
    scenario = write_scenario(work_dir, seconds)
    timing_file, plant_file = work_dir / "ecu_timing.npz", work_dir / "plant.json"
    ecu_log, plant_log = work_dir / "ecu.log", work_dir / "plant.log"
    for stale in (timing_file, plant_file):
        stale.unlink(missing_ok=True)
    python = sys.executable
    hub = subprocess.Popen([python, "-m", "hil.timing.hub"], cwd=REPO_ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           preexec_fn=die_with_parent)
    ecu: subprocess.Popen[Any] | None = None
    scheduling: dict[str, str] = {}
    try:
        line = hub.stdout.readline() if hub.stdout else ""
        if not line.startswith("port "):
            raise TimingRunError(f"the CAN hub did not start: {line!r}")
        port = int(line.split()[1])
        scheduling["hub"] = apply_realtime_policy(placement.plant_cpu, placement.hub_priority,
                                                  pid=hub.pid).describe()
        env = _env(port)
        # both ECUs take the same options; the executable gets the hub's address as options
        # (python-can reads it from CAN_CONFIG)
        program = [str(C_ECU_EXECUTABLE), "--host", "127.0.0.1", "--port", str(port)] if c_ecu \
            else [python, "-m", "firmware_sim"]
        ecu_command = [*program, "--interface", "socketcand",
                       "--channel", CHANNEL, "--controller", controller,
                       "--path", f"1={work_dir / 'path.csv'}", "--realtime",
                       "--timing-out", str(timing_file), "--log-level", "info", "--release", release]
        if placement.ecu_cpu is not None:
            ecu_command += ["--cpu", str(placement.ecu_cpu)]
        if placement.ecu_priority is not None:
            ecu_command += ["--rt-priority", str(placement.ecu_priority)]
        with ecu_log.open("wb") as ecu_out:
            ecu = subprocess.Popen(ecu_command, cwd=REPO_ROOT, env=env, stdin=subprocess.DEVNULL,
                                   stdout=ecu_out, stderr=subprocess.STDOUT,
                                   preexec_fn=die_with_parent)
        _wait_for_ready(ecu, ecu_log)
        plant_command = [python, "-m", "hil.timing.plant_side", "--port", str(port),
                         "--scenario", str(scenario), "--out", str(plant_file)]
        if placement.plant_cpu is not None:
            plant_command += ["--cpu", str(placement.plant_cpu)]
        if placement.plant_priority is not None:
            plant_command += ["--rt-priority", str(placement.plant_priority)]
        times_before = cpu_times()
        with plant_log.open("wb") as plant_out:
            plant_status = subprocess.run(plant_command, cwd=REPO_ROOT, env=env,
                                          stdin=subprocess.DEVNULL, stdout=plant_out,
                                          stderr=subprocess.STDOUT, preexec_fn=die_with_parent,
                                          timeout=seconds + 120.0).returncode
        stolen = steal_share(times_before, cpu_times())
        if plant_status != 0:
            raise TimingRunError(f"the plant process exited with {plant_status}: "
                                 f"{plant_log.read_text(errors='replace')[-1500:]}")
        ecu_status = _stop(ecu)
        if ecu_status != 0 or not timing_file.exists():
            raise TimingRunError(f"the ECU exited with {ecu_status} (timing record written: "
                                 f"{timing_file.exists()}): "
                                 f"{ecu_log.read_text(errors='replace')[-1500:]}")
    finally:
        if ecu is not None:
            _stop(ecu)
        _stop(hub)
        if hub.stdout:
            hub.stdout.close()
    plant = json.loads(plant_file.read_text())
    plant["steal_share"] = stolen
    log_text = ecu_log.read_text(errors="replace")
    scheduling["ecu"] = next((ln.split("scheduling: ", 1)[1] for ln in log_text.splitlines()
                              if "scheduling: " in ln), "not requested")
    scheduling["plant"] = plant.get("scheduling", "")
    return TimingRun(label, seconds, load_timing(timing_file), plant, scheduling, log_text,
                     release)


def _wait_for_ready(ecu: subprocess.Popen[Any], log: Path) -> None:
    give_up = time.monotonic() + ECU_READY_TIMEOUT_S
    while time.monotonic() < give_up:
        if "ready: controller" in log.read_text(errors="replace"):
            return
        if ecu.poll() is not None:
            raise TimingRunError(f"the ECU exited with {ecu.returncode} before it was ready: "
                                 f"{log.read_text(errors='replace')[-1500:]}")
        time.sleep(0.05)
    raise TimingRunError(f"the ECU was not ready within {ECU_READY_TIMEOUT_S:.0f} s")

"""The ECU in real-time mode on an injected clock: absolute releases, input age from the
monotonic arrival time, overruns and the per-cycle timing record."""
from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from can_defs.frames import CtrlMode

from controller.base import Command, SolverStatus, StepDebug, VehicleSample
from firmware_sim.ecu import Ecu
from hil.ecu_harness import PeerNodes, ScriptedController, commands, diags, pump

PATHS = {1: Path("one.csv")}


class FakeClock:
    """Monotonic clock the test moves by hand (seconds)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class SlowController(ScriptedController):
    """Advances the fake clock while it 'computes'."""

    def __init__(self, clock: FakeClock, compute_s: float) -> None:
        super().__init__()
        self.clock, self.compute_s = clock, compute_s

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        self.clock.now += self.compute_s
        return Command(0.01, 50.0), StepDebug(SolverStatus.SOLVED, 3, self.compute_s)


@pytest.fixture
def buses():
    channel = f"ecu-realtime-{uuid.uuid4()}"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    peer_bus = can.Bus(interface="virtual", channel=channel)
    yield ecu_bus, peer_bus
    ecu_bus.shutdown()
    peer_bus.shutdown()


def make(ecu_bus, clock, controller=None) -> tuple[Ecu, ScriptedController]:
    controller = controller or ScriptedController()
    ecu = Ecu(ecu_bus, "scripted", PATHS, lockstep=False, clock=clock,
              controller_factory=lambda name: controller, path_loader=str)
    return ecu, controller


def feed(peers: PeerNodes, ecu: Ecu, ecu_bus: can.BusABC, clock: FakeClock, at: float) -> None:
    clock.now = at
    peers.send_plant(vx=10.0, x=at)
    peers.send_planner()
    pump(ecu, ecu_bus)


def test_releases_every_25_ms_with_input_age_and_jitter_recorded(buses):
    ecu_bus, peer_bus = buses
    clock = FakeClock()
    ecu, controller = make(ecu_bus, clock)
    peers = PeerNodes(peer_bus)
    start = clock.now
    ecu.poll()                                                   # first release at start
    feed(peers, ecu, ecu_bus, clock, start + 0.004)
    clock.now = start + 0.0255                                   # 0.5 ms late
    ecu.poll()
    clock.now = start + 0.030
    ecu.poll()                                                   # not due: nothing
    clock.now = start + 0.050                                    # exactly on time
    ecu.poll()
    sent = peers.received()
    rows = ecu.timing.rows()
    print("modes:", [c.ctrl_mode.name for c in commands(sent)], "\ntiming rows:\n", rows)
    assert len(commands(sent)) == 3 and len(diags(sent)) == 3
    assert rows[:, 0] == pytest.approx([0.0, 0.0005, 0.0], abs=1e-9)       # release jitter
    assert rows[1, 3] == pytest.approx(0.0215, abs=1e-9)                    # input age
    assert rows[2, 3] == pytest.approx(0.046, abs=1e-9)
    assert rows[1, 4] == pytest.approx(0.0215, abs=1e-9)                    # RX -> TX latency
    assert [c.ctrl_mode for c in commands(sent)] == [CtrlMode.INIT, CtrlMode.STANDBY, CtrlMode.STANDBY]
    ecu.close()


def test_realtime_sample_age_uses_monotonic_arrival(buses):
    ecu_bus, peer_bus = buses
    clock = FakeClock()
    ecu, _ = make(ecu_bus, clock)
    peers = PeerNodes(peer_bus)
    start = clock.now
    modes = []
    for k in range(8):
        release = start + 0.025 * k
        if k < 3:
            feed(peers, ecu, ecu_bus, clock, release - 0.001)
        clock.now = release
        ecu.poll()
        modes.append(commands(peers.received())[0].ctrl_mode)
    print("modes:", [m.name for m in modes])
    # last sample arrives 1 ms before release 2: 26 ms old at release 3 -> DEGRADED,
    # 101 ms old at release 6 -> SAFE_STOP
    assert modes == [CtrlMode.STANDBY, CtrlMode.ACTIVE, CtrlMode.ACTIVE, CtrlMode.DEGRADED,
                     CtrlMode.DEGRADED, CtrlMode.DEGRADED, CtrlMode.SAFE_STOP, CtrlMode.SAFE_STOP]
    ecu.close()


def test_task_longer_than_the_period_counts_overruns_and_skips_releases(buses):
    ecu_bus, peer_bus = buses
    clock = FakeClock()
    ecu, _ = make(ecu_bus, clock, SlowController(clock, compute_s=0.060))
    peers = PeerNodes(peer_bus)
    start = clock.now
    for k in range(3):                                            # reach ACTIVE first
        feed(peers, ecu, ecu_bus, clock, start + 0.025 * k)
        ecu.poll()
    assert ecu.mode is CtrlMode.ACTIVE
    overruns_before = ecu.overruns
    feed(peers, ecu, ecu_bus, clock, start + 0.075)
    ecu.poll()                                                    # takes 60 ms: ends at 0.135
    feed(peers, ecu, ecu_bus, clock, clock.now)
    ecu.poll()
    print("overruns:", overruns_before, "->", ecu.overruns,
          "diag OVERRUNS:", [d.overruns for d in diags(peers.received())])
    # the 60 ms task misses its own deadline (1) and release 0.100 is skipped (1); the next
    # 60 ms task (started at 0.135 for release 0.125) misses too (1)
    assert ecu.overruns - overruns_before == 3
    ecu.close()


def test_run_loop_on_the_real_monotonic_clock(buses):
    ecu_bus, peer_bus = buses
    ecu, _ = make(ecu_bus, time.monotonic)
    stop = threading.Event()
    thread = threading.Thread(target=ecu.run, args=(stop,))
    thread.start()
    time.sleep(0.5)
    stop.set()
    thread.join(2.0)
    ecu.close()
    sent = PeerNodes(peer_bus).received()
    summary = ecu.timing.summary()
    print(f"{len(commands(sent))} commands in 0.5 s; release jitter p50 "
          f"{summary['release_jitter']['p50'] * 1e3:.3f} ms, max {summary['release_jitter']['max'] * 1e3:.3f} ms; "
          f"task time p50 {summary['task_time']['p50'] * 1e6:.0f} us")
    assert not thread.is_alive()
    assert 10 <= len(commands(sent)) <= 23          # ~20 releases plus the closing command
    assert summary["task_time"]["n"] == ecu.timing.count

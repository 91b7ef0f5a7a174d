"""Time masters, recorder and run wiring against a minimal contract-only lockstep ECU.

The stub ECU below knows nothing but the contract's lockstep rules: it answers the
handshake, and for every HIL_SYNC it notes which frames arrived since the previous one,
sends a command every 25 ms (before the ACK) and acknowledges the tick. It lets these
tests check the master's side of the protocol independently of firmware_sim.
"""
from __future__ import annotations

import threading
import time

import can
import pytest

from can_defs.codec import FrameSender
from can_defs.frames import CtrlDiag, CtrlMode, QpStatus, SteerTorqueCmd
from hil.bus import BusConfig, open_bus, private_virtual_channel
from hil.plant_node import PlantNode
from hil.planner_node import PlannerNode
from hil.recorder import BusRecorder, EcuFrameMonitor
from hil.scenario import load_scenario
from hil.time_master import (AckTimeoutError, HandshakeTimeoutError, LockstepMaster,
                             PeerDiedError, RealTimeMaster)

HANDSHAKE = 0xFFFFFFFF


def _ack(tick: int) -> can.Message:
    return can.Message(arbitration_id=0x081, data=tick.to_bytes(4, "little") + bytes(4),
                       is_extended_id=False)


class StubLockstepEcu(threading.Thread):
    """Contract-only lockstep ECU on its own virtual bus object (see the module doc)."""

    def __init__(self, channel: str, *, stop_acking_at: int | None = None,
                 steer_per_cycle: float = 0.01) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.stop_acking_at = stop_acking_at
        self.steer_per_cycle = steer_per_cycle
        self.received_per_sync: list[tuple[int, list[int]]] = []
        self.handshakes = 0
        self._halt = threading.Event()
        self._sender = FrameSender()

    def run(self) -> None:
        pending: list[int] = []
        while not self._halt.is_set():
            message = self.bus.recv(timeout=0.02)
            if message is None:
                continue
            if message.arbitration_id != 0x080:
                pending.append(message.arbitration_id)
                continue
            tick = int.from_bytes(bytes(message.data[:4]), "little")
            if tick == HANDSHAKE:
                self.handshakes += 1
                self.bus.send(_ack(HANDSHAKE))
                continue
            self.received_per_sync.append((tick, pending))
            pending = []
            if self.stop_acking_at is not None and tick >= self.stop_acking_at:
                continue
            if tick % 25 == 0:
                cycle = tick // 25
                command = SteerTorqueCmd(CtrlMode.ACTIVE, True, self.steer_per_cycle * cycle, 0.0)
                diag = CtrlDiag(QpStatus.SOLVED, 100, 200, 3, 0, 0)
                for frame in (command, diag):
                    self.bus.send(can.Message(arbitration_id=int(frame.FRAME_ID),
                                              data=self._sender.encode(frame),
                                              is_extended_id=False))
            self.bus.send(_ack(tick))

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2)
        self.bus.shutdown()


@pytest.fixture
def scenario():
    return load_scenario("dlc_smoke")


@pytest.fixture
def bus_config():
    return BusConfig("virtual", private_virtual_channel("test"))


def test_lockstep_sends_due_frames_before_each_sync_and_applies_commands(scenario, bus_config):
    ecu = StubLockstepEcu(bus_config.channel)
    ecu.start()
    master_bus = open_bus(bus_config)
    plant = PlantNode(scenario)
    monitor = EcuFrameMonitor()
    try:
        master = LockstepMaster(master_bus, [plant, PlannerNode(scenario), monitor],
                                handshake_timeout_s=2.0, ack_timeout_s=2.0)
        stats = master.run(0.1)
    finally:
        ecu.stop()
        master_bus.shutdown()
    print("stats", stats, "ECU saw", ecu.received_per_sync[:6])
    assert ecu.handshakes >= 1
    assert [tick for tick, _ in ecu.received_per_sync] == list(range(0, 100, 5))
    for tick, ids in ecu.received_per_sync:
        expected = ([0x100, 0x101, 0x102] if tick % 10 == 0 else []) + \
                   ([0x110] if tick % 25 == 0 else [])
        assert ids == expected, f"frames before HIL_SYNC TICK={tick}: {ids}"
    assert stats.ticks == 20
    # The command sent before the ACK of tick t is applied for t -> t + 5 ms.
    steer_cmd = plant.trace()["steer_cmd"]
    assert steer_cmd[5] == pytest.approx(0.01) and steer_cmd[4] == pytest.approx(0.0)
    assert steer_cmd[15] == pytest.approx(0.03)
    assert len(monitor.commands) == 4 and len(monitor.diags) == 4


def test_ack_timeout_names_the_tick(scenario, bus_config):
    ecu = StubLockstepEcu(bus_config.channel, stop_acking_at=35)
    ecu.start()
    master_bus = open_bus(bus_config)
    try:
        master = LockstepMaster(master_bus, [PlannerNode(scenario)], handshake_timeout_s=2.0,
                                ack_timeout_s=0.3)
        with pytest.raises(AckTimeoutError, match="TICK=35 ms") as error:
            master.run(1.0)
    finally:
        ecu.stop()
        master_bus.shutdown()
    print(error.value)


def test_handshake_repeats_every_100_ms_then_gives_up(bus_config):
    listener = open_bus(bus_config)
    master_bus = open_bus(bus_config)
    try:
        master = LockstepMaster(master_bus, [], handshake_timeout_s=0.45)
        started = time.monotonic()
        with pytest.raises(HandshakeTimeoutError, match="did not answer") as error:
            master.handshake()
        elapsed = time.monotonic() - started
        stamps = []
        while (message := listener.recv(timeout=0.0)) is not None:
            assert message.arbitration_id == 0x080
            assert int.from_bytes(bytes(message.data[:4]), "little") == HANDSHAKE
            stamps.append(message.timestamp)
    finally:
        listener.shutdown()
        master_bus.shutdown()
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    print(f"{error.value}; {len(stamps)} handshakes in {elapsed:.2f} s, gaps {gaps}")
    assert 4 <= len(stamps) <= 6
    assert all(0.09 <= gap <= 0.2 for gap in gaps)


def test_a_dead_ecu_is_reported_at_once(bus_config):
    master_bus = open_bus(bus_config)
    try:
        master = LockstepMaster(master_bus, [], handshake_timeout_s=30.0,
                                peer_alive=lambda: "ECU process exited with status 2")
        started = time.monotonic()
        with pytest.raises(PeerDiedError, match="status 2"):
            master.handshake()
    finally:
        master_bus.shutdown()
    assert time.monotonic() - started < 1.0


class _CountingNode:
    """Light node for the real-time loop: counts ticks and frames."""

    def __init__(self) -> None:
        self.ticks: list[int] = []
        self.received: list[int] = []

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        return [can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False)] \
            if tick_ms % 10 == 0 else []

    def receive(self, message: can.Message, tick_ms: int) -> None:
        self.received.append(message.arbitration_id)

    def advance(self, tick_ms: int, dt_s: float) -> None:
        self.ticks.append(tick_ms)


def test_real_time_master_keeps_absolute_deadlines(bus_config):
    node = _CountingNode()
    peer = open_bus(bus_config)
    master_bus = open_bus(bus_config)
    try:
        peer.send(can.Message(arbitration_id=0x200, data=bytes(8), is_extended_id=False))
        started = time.monotonic()
        stats = RealTimeMaster(master_bus, [node]).run(0.3)
        elapsed = time.monotonic() - started
        seen_by_peer = 0
        while peer.recv(timeout=0.0) is not None:
            seen_by_peer += 1
    finally:
        peer.shutdown()
        master_bus.shutdown()
    print(f"60 ticks in {elapsed:.3f} s, overruns {stats.overruns}, "
          f"max lateness {stats.max_lateness_s * 1e3:.2f} ms")
    assert node.ticks == list(range(0, 300, 5))
    assert node.received == [0x200]
    assert seen_by_peer == 30
    # Absolute deadlines: the run ends on the last deadline, not later by accumulated error.
    assert 0.29 <= elapsed <= 0.4


@pytest.mark.parametrize("suffix", [".log", ".asc", ".csv"])
def test_recorder_keeps_every_frame_in_the_format_of_the_suffix(tmp_path, scenario, bus_config,
                                                                suffix):
    ecu = StubLockstepEcu(bus_config.channel)
    ecu.start()
    master_bus = open_bus(bus_config)
    log = tmp_path / f"run{suffix}"
    recorder = BusRecorder(open_bus(bus_config), log)
    try:
        master = LockstepMaster(master_bus, [PlannerNode(scenario)], handshake_timeout_s=2.0)
        stats = master.run(0.1)
        expected = stats.frames_sent + stats.frames_received
        assert recorder.wait_for(expected, timeout_s=2.0)
    finally:
        recorder.stop()
        ecu.stop()
        master_bus.shutdown()
    frames = list(can.LogReader(log))
    print(f"{suffix}: {len(frames)} frames recorded, master counted {expected}")
    assert len(frames) == expected
    # Per tick: PLANNER_REQ when due, HIL_SYNC, the ECU's answer, ACK. (The handshake
    # may repeat on a busy machine, so its frames are left out of the comparison.)
    ids = [frame.arbitration_id for frame in frames
           if bytes(frame.data[:4]) != HANDSHAKE.to_bytes(4, "little")]
    expected_ids = []
    for tick in range(0, 100, 5):
        due = tick % 25 == 0
        expected_ids += [0x110] * due + [0x080] + [0x200, 0x201] * due + [0x081]
    assert ids == expected_ids

"""Test helpers for driving an `Ecu` without a plant: a scripted controller and the peer
nodes (plant, planner, time master) on their own bus object.

Used by ``tests/test_ecu*.py`` and the ECU overhead of ``studies.bench``; also handy to poke an ECU by
hand. Not imported by the ECU.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import can
from can_defs.codec import FrameSender, decode, encode
from can_defs.frames import (HANDSHAKE_TICK, CtrlDiag, FrameId, HilSync, PlannerReq,
                             SteerTorqueCmd, VehDyn, VehPoseXY, VehPoseYaw)

from controller.base import Command, Controller, SolverStatus, StepDebug, VehicleSample


@dataclass
class ScriptedController(Controller):
    """Controller double: steer = ``gain * sample.y`` (clipped to 0.3 rad), torque =
    ``torque``; records every call. ``raise_on_step`` / ``nan_command`` inject failures;
    ``fall_back``: the law's own fallback (its last command again, ``debug.fallback``, as
    an MPC whose solver failed)."""

    name: str = "scripted"
    gain: float = -0.01
    torque: float = 100.0
    raise_on_step: bool = False
    nan_command: bool = False
    command_override: Command | None = None
    fall_back: bool = False
    solve_time_s: float = 0.0012
    samples: list[VehicleSample] = field(default_factory=list)
    paths: list[object] = field(default_factory=list)
    resets: int = 0
    last_command: Command = Command(0.0, 0.0)

    def set_path(self, path: object) -> None:
        self.paths.append(path)

    def reset(self) -> None:
        self.resets += 1

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        self.samples.append(sample)
        if self.raise_on_step:
            raise RuntimeError("scripted controller failure")
        if self.nan_command:
            return Command(math.nan, self.torque), StepDebug(SolverStatus.NUMERICAL_ERROR)
        if self.command_override is not None:
            return self.command_override, StepDebug(SolverStatus.SOLVED, 7, self.solve_time_s)
        if self.fall_back:
            return self.last_command, StepDebug(SolverStatus.MAX_ITERATIONS, 7, self.solve_time_s, fallback=True)
        steer = min(max(self.gain * sample.y, -0.3), 0.3)
        self.last_command = Command(steer, self.torque)
        return self.last_command, StepDebug(SolverStatus.SOLVED, 7, self.solve_time_s)


def pump(ecu: object, bus: can.BusABC) -> int:
    """Hand every frame waiting on ``bus`` to ``ecu.handle_message``; returns the count."""
    handled = 0
    while (message := bus.recv(0.0)) is not None:
        ecu.handle_message(message)  # type: ignore[attr-defined]
        handled += 1
    return handled


class PeerNodes:
    """Plant, planner and time master frames onto one bus (``bus`` is the peers' object)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.plant_counter = 0
        self._planner = FrameSender()

    def send_raw(self, frame_id: int, data: bytes) -> None:
        """Put a payload on the bus as it is (for corrupt frames)."""
        self.bus.send(can.Message(arbitration_id=int(frame_id), data=data, is_extended_id=False))

    def send_plant(self, *, vx: float = 10.0, vy: float = 0.0, yaw_rate: float = 0.0,
                   x: float = 0.0, y: float = 0.0, yaw: float = 0.0, steer_angle: float = 0.0,
                   drive_torque: float = 0.0, counter: int | None = None,
                   skip: tuple[FrameId, ...] = ()) -> int:
        """The three plant frames of one instant with one counter (next one by default);
        frames in ``skip`` are not sent (a torn sample). Returns the counter used."""
        used = self.plant_counter if counter is None else counter
        frames = (VehDyn(vx, vy, yaw_rate), VehPoseXY(x, y),
                  VehPoseYaw(yaw, steer_angle, drive_torque))
        for frame in frames:
            if frame.FRAME_ID not in skip:
                self.send_raw(frame.FRAME_ID, encode(frame, used))
        self.plant_counter = (used + 1) % 16
        return used

    def send_planner(self, engage: bool = True, target_speed: float = 10.0, path_id: int = 1) -> None:
        """One PLANNER_REQ with the planner's next alive counter."""
        frame = PlannerReq(engage, target_speed, path_id)
        self.send_raw(FrameId.PLANNER_REQ, self._planner.encode(frame))

    def send_sync(self, tick: int) -> None:
        """HIL_SYNC with ``tick`` (ms, or the handshake value)."""
        self.send_raw(FrameId.HIL_SYNC, encode(HilSync(tick)))

    def send_handshake(self) -> None:
        """HIL_SYNC 0xFFFFFFFF."""
        self.send_sync(HANDSHAKE_TICK)

    def received(self) -> list[can.Message]:
        """Every frame the ECU sent that is waiting on the peers' bus."""
        messages = []
        while (message := self.bus.recv(0.0)) is not None:
            messages.append(message)
        return messages


def decode_messages(messages: list[can.Message]) -> list[object]:
    """Typed frames of ``messages`` (in order)."""
    return [decode(message.arbitration_id, bytes(message.data)).frame for message in messages]


def commands(messages: list[can.Message]) -> list[SteerTorqueCmd]:
    """The STEER_TORQUE_CMD frames among ``messages``."""
    return [frame for frame in decode_messages(messages) if isinstance(frame, SteerTorqueCmd)]


def diags(messages: list[can.Message]) -> list[CtrlDiag]:
    """The CTRL_DIAG frames among ``messages``."""
    return [frame for frame in decode_messages(messages) if isinstance(frame, CtrlDiag)]

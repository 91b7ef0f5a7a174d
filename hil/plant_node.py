"""Plant emulator node: the four-wheel vehicle behind the CAN contract.

Every 10 ms it publishes VEH_DYN, VEH_POSE_XY and VEH_POSE_YAW carrying the state of
one sample instant (every 25 ms, at the ticks that are multiples of 25, as a plant of
contract revision 3 may: ``sample_period_ms``). The three frames are always sent together and each has its own
alive counter starting at 0, so one `FrameSender` gives all three the same CNT: the
ECU's consistency check (one counter = one sample) holds by construction.

It receives STEER_TORQUE_CMD through an E2E receiver and applies the newest accepted
command only while CMD_VALID = 1; otherwise it holds the last applied steering angle and
applies zero drive torque (docs/can-contract.md, "Receiving rules"). The steering command is
saturated at +-0.3 rad as the contract's actuator does (the vehicle model saturates too).

The node holds no clock: the time master (lockstep or wall clock) calls
`frames_due(tick_ms)`, `receive(message)` and `advance(tick_ms, dt_s)`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from can_defs.codec import FrameSender, decode
from can_defs.e2e import E2EReceiver
from can_defs.errors import CanDefsError
from can_defs.frames import (FrameId, SteerTorqueCmd, VehDyn, VehPoseXY, VehPoseYaw)
from controller.base import STEER_LIMIT_RAD
from hil.errors import HilError
from hil.scenario import Scenario
from models.vehicle import FourWheelVehicle, VehicleCommand, VehicleOutputs

#: Publishing period of the three plant frames (contract: 10 ms).
PLANT_PERIOD_MS = 10
#: Periods a plant may publish at (contract rev. 3: 25 ms for a plant that knows it).
PLANT_PERIODS_MS = (10, 25)
#: Without a valid command for this long the plant stops driving (actuator watchdog:
#: steering held, zero torque), so a dead ECU never leaves the last torque applied.
COMMAND_TIMEOUT_MS = 100

#: Columns of the plant's time series (one row per tick, state at the tick's start).
TRACE_COLUMNS = ("time", "vx", "vy", "yaw_rate", "x", "y", "yaw", "steer", "torque",
                 "steer_cmd", "torque_cmd", "ctrl_mode", "cmd_valid")


class PlantFaultError(HilError):
    """The scenario's ``[faults]`` table asks the plant for something invalid."""


@dataclass(frozen=True)
class MuStep:
    """A step of the road friction at ``time_s`` (s) to ``mu``."""

    time_s: float
    mu: float


def mu_step_from_faults(faults: Mapping[str, Any], source: object = "scenario") -> MuStep | None:
    """The plant's own fault from a scenario ``[faults]`` table: ``mu_step = {time_s, mu}``.

    Other keys belong to other injectors (bus faults) and are ignored here.

    Raises:
        PlantFaultError: ``mu_step`` is not a table with finite ``time_s`` >= 0 and
            ``mu`` in (0, 2].
    """
    raw = faults.get("mu_step")
    if raw is None:
        return None
    if not isinstance(raw, Mapping) or set(raw) != {"time_s", "mu"}:
        raise PlantFaultError(f"{source}: faults.mu_step = {raw!r}: must be a table with "
                              "exactly time_s and mu")
    time_s, mu = raw["time_s"], raw["mu"]
    for name, value in (("time_s", time_s), ("mu", mu)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise PlantFaultError(f"{source}: faults.mu_step.{name} = {value!r}: must be a "
                                  "finite number")
    if time_s < 0:
        raise PlantFaultError(f"{source}: faults.mu_step.time_s = {time_s!r}: must be >= 0")
    if not 0.0 < mu <= 2.0:
        raise PlantFaultError(f"{source}: faults.mu_step.mu = {mu!r}: must be in (0, 2]")
    return MuStep(float(time_s), float(mu))


class PlantNode:
    """The HIL plant: vehicle model, its three output frames and the command input.

    Args:
        scenario: road friction, mass, start state, faults and disturbances of the run.
        vehicle: a ready vehicle (tests); default: built from the scenario.
        sample_period_ms: publishing period, 10 ms (the contract) or 25 ms (revision 3,
            for an ECU with ``--release sample --plant-period 25``).

    Raises:
        HilError: a period other than 10 or 25 ms.
    """

    def __init__(self, scenario: Scenario, vehicle: FourWheelVehicle | None = None,
                 sample_period_ms: int = PLANT_PERIOD_MS) -> None:
        if sample_period_ms not in PLANT_PERIODS_MS:
            raise HilError(f"plant sample_period_ms must be 10 or 25, got {sample_period_ms!r}")
        self.sample_period_ms = sample_period_ms
        self.scenario = scenario
        self.vehicle = vehicle if vehicle is not None else scenario.vehicle()
        start = scenario.start
        self.vehicle.reset(vx=start.speed_mps, x=start.x_m, y=start.y_m, yaw=start.yaw_rad)
        self.mu_step = mu_step_from_faults(scenario.faults, scenario.source)
        self._sender = FrameSender()
        self._command_rx = E2EReceiver(FrameId.STEER_TORQUE_CMD)
        self._newest: SteerTorqueCmd | None = None
        self._newest_tick_ms: int | None = None
        self._last_valid_tick_ms: int | None = None
        self.applied = VehicleCommand(drive_torque=0.0, steer_angle=0.0)
        self.last_command: SteerTorqueCmd | None = None
        self.commands_received = 0
        self.commands_rejected = 0
        self._trace: list[tuple[float, ...]] = []

    # --- bus side -------------------------------------------------------------------

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        """The plant frames due at ``tick_ms`` (state now), empty between periods."""
        if tick_ms % self.sample_period_ms:
            return []
        out = self.vehicle.outputs()
        frames = (VehDyn(out.vx, out.vy, out.yaw_rate),
                  VehPoseXY(out.x, out.y),
                  VehPoseYaw(out.yaw, out.steer_angle, out.drive_torque))
        return [can.Message(arbitration_id=int(f.FRAME_ID), data=self._sender.encode(f),
                            is_extended_id=False) for f in frames]

    def receive(self, message: can.Message, tick_ms: int) -> None:
        """Take one received frame; only STEER_TORQUE_CMD concerns the plant."""
        if message.arbitration_id != FrameId.STEER_TORQUE_CMD or message.is_extended_id:
            return
        self.commands_received += 1
        if not self._command_rx.check(bytes(message.data)).accepted:
            self.commands_rejected += 1
            return
        try:
            frame = decode(message.arbitration_id, bytes(message.data)).frame
        except CanDefsError:  # undefined CTRL_MODE: not a command we can trust
            self.commands_rejected += 1
            return
        self._newest = frame
        self._newest_tick_ms = tick_ms

    # --- physics side ---------------------------------------------------------------

    def apply_newest_command(self, tick_ms: int) -> VehicleCommand:
        """Latch the newest accepted command (contract: only while CMD_VALID = 1)."""
        newest, self._newest = self._newest, None
        if newest is not None:
            self.last_command = newest
            if newest.cmd_valid:
                steer = min(max(newest.steer_angle_cmd, -STEER_LIMIT_RAD), STEER_LIMIT_RAD)
                self.applied = VehicleCommand(drive_torque=newest.drive_torque_cmd,
                                              steer_angle=steer)
                self._last_valid_tick_ms = tick_ms
            else:
                self.applied = VehicleCommand(drive_torque=0.0,
                                              steer_angle=self.applied.steer_angle)
        elif (self._last_valid_tick_ms is not None
              and tick_ms - self._last_valid_tick_ms > COMMAND_TIMEOUT_MS
              and self.applied.drive_torque != 0.0):
            self.applied = VehicleCommand(drive_torque=0.0, steer_angle=self.applied.steer_angle)
        return self.applied

    def advance(self, tick_ms: int, dt_s: float) -> None:
        """Apply the newest command, record the state at ``tick_ms``, integrate ``dt_s``."""
        command = self.apply_newest_command(tick_ms)
        self._record(tick_ms, self.vehicle.true_outputs(), command)
        if self.mu_step is not None and tick_ms / 1000.0 >= self.mu_step.time_s \
                and self.vehicle.mu != self.mu_step.mu:
            self.vehicle.set_friction(self.mu_step.mu)
        self.vehicle.step(command, dt_s)

    def restart_node(self) -> None:
        """Restart the node's software (counters from 0, command input forgotten); the
        vehicle itself keeps moving, as a real car would while its gateway reboots."""
        self._sender = FrameSender()
        self._command_rx = E2EReceiver(FrameId.STEER_TORQUE_CMD)
        self._newest = None

    # --- results ----------------------------------------------------------------------

    def _record(self, tick_ms: int, out: VehicleOutputs, command: VehicleCommand) -> None:
        last = self.last_command
        self._trace.append((tick_ms / 1000.0, out.vx, out.vy, out.yaw_rate, out.x, out.y,
                            out.yaw, out.steer_angle, out.drive_torque,
                            command.steer_angle, command.drive_torque,
                            float(last.ctrl_mode) if last is not None else float("nan"),
                            float(last.cmd_valid) if last is not None else float("nan")))

    def trace(self) -> dict[str, np.ndarray]:
        """Recorded time series: column name -> array of shape (n_ticks,)
        (columns :data:`TRACE_COLUMNS`; the true state at each tick before integrating:
        without a scenario's yaw-rate bias, ``steer`` the true wheel angle with its
        steering offset; the frames carry what the sensors report)."""
        table = np.array(self._trace, dtype=float).reshape(-1, len(TRACE_COLUMNS))
        return {name: table[:, i].copy() for i, name in enumerate(TRACE_COLUMNS)}

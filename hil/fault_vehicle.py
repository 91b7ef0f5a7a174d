"""Vehicle faults of the HIL's plant that the vehicle model has no parameter for: a
misaligned steering rack (`OffsetSteeringVehicle`), built by
``hil.fault_injector.FaultInjector.vehicle`` with the spec's other vehicle faults.
"""
from __future__ import annotations

from typing import Any

from models.vehicle import FourWheelVehicle, VehicleCommand


class OffsetSteeringVehicle(FourWheelVehicle):
    """A vehicle whose steering actuator settles at command + offset (a misaligned rack);
    the measured STEER_ANGLE is the true wheel angle, offset included. (A scenario's
    ``[disturbances] steer_offset_rad`` is the other kind: the wheels sit off the
    actuator's state, which STEER_ANGLE reports, so the offset is not seen.)"""

    def __init__(self, params: Any, offset_rad: float, disturbances: Any = None) -> None:
        super().__init__(params, disturbances=disturbances)
        self.steer_offset_rad = offset_rad

    def step(self, command: VehicleCommand, dt: float) -> Any:
        """Step with the offset added to the steering command (the model saturates it)."""
        return super().step(VehicleCommand(drive_torque=command.drive_torque,
                                           steer_angle=command.steer_angle + self.steer_offset_rad), dt)

"""Longitudinal P speed controller of the decoupled structure (paper Section III, Fig. 4)."""
from __future__ import annotations

from controller.tuning import LongitudinalTuning


class SpeedController:
    """Total drive torque (N m) from the speed error: T = K_p (v_target - v_x), clipped.

    Stateless: the same sample always gives the same torque.
    """

    def __init__(self, tuning: LongitudinalTuning) -> None:
        self.tuning = tuning

    def torque(self, vx: float, target_speed: float) -> float:
        """Torque command (N m) for measured ``vx`` and ``target_speed`` (m/s)."""
        torque = self.tuning.speed_gain * (target_speed - vx)
        return self.clip(torque)

    def clip(self, torque: float) -> float:
        """Torque clipped to [torque_min, torque_max]."""
        return min(max(torque, self.tuning.torque_min), self.tuning.torque_max)

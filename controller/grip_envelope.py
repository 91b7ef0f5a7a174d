"""Grip envelope: a yaw-rate bound from the road's grip, estimated from the rear axle's slip.

No signal on the bus carries the road's friction, and the MPCs' models do not saturate: on
a slippery road they ask for more yaw rate than the tyres can give, the rear axle slides
and the car spins (make identify's changed plant on the low-mu lane change). An ESC unit
bounds the yaw rate by the lateral acceleration the road supports, a_max / vx; this module
estimates a_max from the measured states and the nominal bicycle (models/vehicle.toml),
and the QP MPCs put the bound on the yaw-rate rows of eq. 21 (``controller.steering_qp``).

Per valid sample (vx above ``MIN_SPEED_M_S``), with Ts the control period:

    a_y   = (vy - vy_prev) / Ts + r vx                  measured lateral acceleration (m/s^2)
    alpha = (lr r - vy) / vx                            the rear axle's slip angle (rad)
    alpha_lin = m lf / L * a_y / Cr                     the slip a linear rear tyre needs for a_y
    peak  = max(|a_y|, peak * exp(-Ts / peak_time))     the recent peak of |a_y|
    if |alpha| - |alpha_lin| > slip_excess:             the rear axle slides: the grip is reached
        grip = max(peak, MIN_GRIP_M_S2)
    else:
        grip = min(grip + recovery * Ts, MAX_GRIP_M_S2)

and the yaw-rate bound is (1 + margin) * grip / vx (rad/s), no wider than the table's
state_max / state_min; at ``MAX_GRIP_M_S2`` (no evidence of a limit) there is no bound at
all, so that a table with the envelope on solves the same QP as one with it off until the
rear axle first slides. Only the rear axle counts: a sliding front axle makes the car
understeer, which is stable, while a sliding rear axle is the start of a spin. The front
axle's slip is left out for a second reason: a steering offset (a misaligned rack) shifts
it by the offset itself. The estimate starts at ``MAX_GRIP_M_S2`` (no bound) and returns
there at ``recovery`` once the rear axle grips again.

The C core implements the same (firmware/src/ecu_grip.c). Control math only: no bus, no
clock; Ts is the contract's control period (the samples of successive steps are 20 to 30 ms
apart at the contract's 10 ms publication, which the difference quotient ignores).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from controller.base import CONTROL_PERIOD_S, VehicleSample
from controller.tuning import MpcTuning

#: Below this speed (m/s) the slip angles are ill-conditioned: no update, no bound.
MIN_SPEED_M_S = 3.0
#: The estimate's floor (m/s^2): a grip below it is taken as a transient, not the road.
MIN_GRIP_M_S2 = 2.0
#: The estimate with no evidence of a limit (m/s^2): above any tyre's grip (mu 1.2 g).
MAX_GRIP_M_S2 = 12.0


@dataclass(frozen=True)
class RearAxle:
    """The nominal bicycle's numbers the estimate needs: mass (kg), lf, lr (m) and the rear
    axle's cornering stiffness Cr (N/rad)."""

    mass: float
    lf: float
    lr: float
    cornering_stiffness_rear: float

    @classmethod
    def nominal(cls) -> "RearAxle":
        """From models/vehicle.toml, as LMPC's bicycle (``models.bicycle.nominal_model_params``)."""
        from models.bicycle import nominal_model_params

        p = nominal_model_params()
        return cls(p.mass, p.lf, p.lr, p.cornering_stiffness_rear)

    def linear_slip(self, lateral_accel: float) -> float:
        """The rear slip angle (rad) a linear tyre needs for ``lateral_accel`` (m/s^2) in a
        steady turn: the rear axle carries m lf / L of the lateral force."""
        return self.mass * self.lf / (self.lf + self.lr) * lateral_accel / self.cornering_stiffness_rear


def envelope_on(tuning: MpcTuning) -> bool:
    """Whether an MPC's tuning table switches the envelope on (``grip_slip_excess`` > 0):
    then the MPC builds a ``GripEnvelope`` on the nominal rear axle (models/vehicle.toml)."""
    return tuning.grip_slip_excess > 0.0


class GripEnvelope:
    """The estimate above; ``update`` once per valid sample, before the plan."""

    def __init__(self, tuning: MpcTuning, axle: RearAxle, ts: float = CONTROL_PERIOD_S) -> None:
        self.slip_excess = tuning.grip_slip_excess
        self.margin = tuning.grip_margin
        self.recovery_step = tuning.grip_recovery * ts
        # exp once here: the C core computes the same factor at start-up with the same libm.
        self.peak_decay = math.exp(-ts / tuning.grip_peak_time)
        self.axle = axle
        self.ts = ts
        self.reset()

    @property
    def enabled(self) -> bool:
        """Whether the table switches the envelope on (`envelope_on`)."""
        return self.slip_excess > 0.0

    def reset(self) -> None:
        """Forget the previous sample and the estimate (no bound)."""
        self.previous_vy: float | None = None
        self.peak = 0.0
        self.grip = MAX_GRIP_M_S2
        self.sliding = False

    def update(self, sample: VehicleSample) -> float:
        """Advance the estimate with ``sample`` (finite) and return the yaw-rate bound (rad/s,
        > 0; ``math.inf`` when off, below ``MIN_SPEED_M_S``, on the first sample or with the
        estimate at ``MAX_GRIP_M_S2``)."""
        if not self.enabled:
            return math.inf
        previous, self.previous_vy = self.previous_vy, sample.vy
        if previous is None or sample.vx < MIN_SPEED_M_S:
            return math.inf
        lateral_accel = (sample.vy - previous) / self.ts + sample.yaw_rate * sample.vx
        rear_slip = (self.axle.lr * sample.yaw_rate - sample.vy) / sample.vx
        self.peak = max(abs(lateral_accel), self.peak * self.peak_decay)
        self.sliding = abs(rear_slip) - abs(self.axle.linear_slip(lateral_accel)) > self.slip_excess
        if self.sliding:
            self.grip = max(self.peak, MIN_GRIP_M_S2)
        else:
            self.grip = min(self.grip + self.recovery_step, MAX_GRIP_M_S2)
        if self.grip >= MAX_GRIP_M_S2:
            return math.inf
        return (1.0 + self.margin) * self.grip / sample.vx

"""Yaw-rate sensor bias from the measured heading: the observer's output disturbance.

The lifted ESO (models.eso) estimates disturbances of the dynamics. A bias b of the yaw-rate
sensor is not one: it is an error of a measured output, and from the vehicle states alone it
cannot be told apart from a yaw-moment disturbance. The heading can: the plant reports it
(VEH_POSE_YAW) from another sensor, and its change over a step is the true yaw rate. So the
one-step residual

    e_k = (r_k + r_{k-1}) / 2 - wrap(yaw_k - yaw_{k-1}) / Ts

(trapezoidal mean of the measured rate against the heading's difference quotient) equals b
plus the discretisation and quantisation errors, and a first-order filter

    b_hat[k] = b_hat[k-1] + (1 - pole) (e_k - b_hat[k-1])

estimates b with a time constant of about Ts / (1 - pole). The ECU's samples are 20 or 30 ms
apart (10 ms plant frames, 25 ms task), so e_k alternates around b by up to a fifth of the
yaw rate; a slow pole averages that out. The observer then works on the corrected rate
r_k - b_hat[k]: the bias becomes a known output offset and the MPC no longer steers against
a rotation that is not there.

Pure functions of (state, sample, parameters); ``pole`` 1 keeps the estimate at zero.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class YawRateBiasState:
    """The estimate ``bias`` (rad/s) and the previous sample's heading (rad) and measured
    yaw rate (rad/s); ``previous_yaw`` None: no previous sample (start, or after a gap)."""

    bias: float = 0.0
    previous_yaw: float | None = None
    previous_yaw_rate: float = 0.0


def yaw_rate_bias_update(state: YawRateBiasState, yaw: float, yaw_rate: float, pole: float,
                         ts: float) -> YawRateBiasState:
    """One filter step with the sample's heading ``yaw`` (rad) and measured ``yaw_rate``
    (rad/s), control period ``ts`` (s). A non-finite sample keeps the estimate and forgets
    the previous sample (no update across a gap); so does a step whose estimate would not be
    finite."""
    if not (math.isfinite(yaw) and math.isfinite(yaw_rate)):
        return YawRateBiasState(state.bias)
    if state.previous_yaw is None:
        return YawRateBiasState(state.bias, yaw, yaw_rate)
    heading_rate = math.remainder(yaw - state.previous_yaw, 2.0 * math.pi) / ts
    residual = 0.5 * (yaw_rate + state.previous_yaw_rate) - heading_rate
    bias = state.bias + (1.0 - pole) * (residual - state.bias)
    if not math.isfinite(bias):
        return YawRateBiasState(state.bias, yaw, yaw_rate)
    return YawRateBiasState(bias, yaw, yaw_rate)

"""The heading target under a constant disturbance: the measured side slip.

Under a steady crosswind, on a banked road or with a steering offset, the car holds a
straight line only while it drives with a side-slip angle: its velocity is along the path,
its heading is not. An MPC whose yaw cost pulls the heading onto the path's then trades a
standing lateral error against that heading error, however well its model or observer knows
the disturbance (shared/spec/offset-free.md: the steady target must be one the plant can
hold). The lateral error moves at vx sin(e_yaw) + vy cos(e_yaw), so the target that costs
nothing at zero lateral error is the course (heading plus side slip vy / vx) on the path's
heading. This module gives that target from the step's measured side slip:

- ``reference_bend(yaw)`` (rad): how far the horizon's reference heading departs from the
  straight line between its ends; 0 on a straight and on an arc of constant curvature.
- ``slip_target(slip, bend, limit, gate)`` (rad): the slip, bounded by ``limit`` and faded
  out as the bend grows to ``gate``. In a manoeuvre (a lane change) the slip is the tyres'
  transient, which the prediction already carries, not a steady state to hold.

The slip is measured, not taken from the model's steady state under the observer's
estimate: that map (vy_steady = L w, from (I - A) of the lifted model) is nearly singular in
directions the learned lift spans, |L| reached 340-2240 and turned model error into slips
of up to 0.048 rad on a nominal drive (docs/eso.md).
"""
from __future__ import annotations

import numpy as np

#: Speed (m/s) below which the side slip vy / vx is taken at this speed instead.
SLIP_MIN_SPEED = 1.0


def measured_slip(vy: float, vx: float) -> float:
    """The side slip (rad, small angle) of a sample: vy / max(vx, SLIP_MIN_SPEED)."""
    return vy / max(vx, SLIP_MIN_SPEED)
def reference_bend(yaw: np.ndarray) -> float:
    """Largest departure (rad) of the reference heading (Np,) over the horizon from the
    straight line between its first and last entries (unwrapped)."""
    heading = np.unwrap(np.asarray(yaw, dtype=float))
    n = heading.shape[0]
    if n < 3:
        return 0.0
    line = heading[0] + (heading[-1] - heading[0]) * (np.arange(n) / (n - 1))
    return float(np.max(np.abs(heading - line)))


def slip_target(slip: float, bend: float, limit: float, gate: float) -> float:
    """The side slip (rad) the heading target moves by: ``slip`` bounded by +-``limit``
    and scaled by max(0, 1 - bend / gate); 0 when ``limit`` is 0 or the slip is not
    finite."""
    if limit <= 0.0 or not np.isfinite(slip) or not np.isfinite(bend):
        return 0.0
    fade = min(max(1.0 - bend / gate, 0.0), 1.0)
    return min(max(slip, -limit), limit) * fade

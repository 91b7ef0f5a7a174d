"""The heading target under a constant disturbance: the observer's steady side slip.

Under a steady crosswind, on a banked road or with a steering offset, the car holds a
straight line only while it drives with a side-slip angle: its velocity is along the path,
its heading is not. An MPC whose yaw cost pulls the heading onto the path's then trades a
standing lateral error against that heading error, however well its observer knows the
disturbance (shared/spec/offset-free.md: the MPC must compute its steady target with the
estimate). This module gives the target: the side slip the estimate w_hat implies in the
model's steady state on a straight road, so the yaw cost acts on heading + slip (the
course angle the disturbance requires) instead of the heading.

- ``steady_slip_map(A, B, vy_row, yaw_rate_row, vx_row)`` (n,): the row L with
  vy_steady = L @ w, from the steady state of x = A x + B u + c + w at zero yaw rate and
  the present speed, the inputs free. It is linear in w (the model's own steady state,
  c, cancels), so it is built once per linear model (per speed quantum).
- ``reference_bend(yaw)`` (rad): how far the horizon's reference heading departs from the
  straight line between its ends; 0 on a straight and on an arc of constant curvature.
- ``slip_target(slip, bend, limit, gate)`` (rad): the slip, bounded by ``limit`` and faded
  out as the bend grows to ``gate``. In a manoeuvre (a lane change) the estimate holds the
  tyres' transients, not a steady disturbance, and a target from it made the low-friction
  lane change worse (docs/eso.md).
"""
from __future__ import annotations

import numpy as np


def steady_slip_map(A: np.ndarray, B: np.ndarray, vy_row: int, yaw_rate_row: int,
                    vx_row: int | None = None) -> np.ndarray:
    """Row L (n,) with vy_steady = L @ w for a disturbance w (n,) of x+ = A x + B u + c + w.

    Args:
        A: (n, n) state matrix of the model at this speed.
        B: (n, m) input matrix; every input is free in the steady state.
        vy_row, yaw_rate_row: rows of vy and the yaw rate in x.
        vx_row: row of vx, held at its present value (the speed controller owns it);
            None for a model without a vx state. Then m must be 1 (the steering).

    Returns:
        L (n,); zeros when the steady state is not unique (a singular system).
    """
    n, m = B.shape
    held = [yaw_rate_row] + ([] if vx_row is None else [vx_row])
    size = n + m
    if len(held) != m:
        raise ValueError(f"{m} inputs need {m} held states, got {len(held)} (vx_row {vx_row})")
    system = np.zeros((size, size))
    system[:n, :n] = np.eye(n) - A
    system[:n, n:] = -B
    for k, row in enumerate(held):
        system[n + k, row] = 1.0
    # vy_steady = e_vy^T system^-1 [w; 0]: one solve with the transpose gives the row
    selector = np.zeros(size)
    selector[vy_row] = 1.0
    try:
        row = np.linalg.solve(system.T, selector)
    except np.linalg.LinAlgError:
        return np.zeros(n)
    if not np.all(np.isfinite(row)):
        return np.zeros(n)
    return np.ascontiguousarray(row[:n])


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

"""The steering servo's time constant from driving data: a first-order lag of the measured
wheel angle behind the commanded one, fitted by least squares.

Why: a vehicle whose steering answers more slowly than the one a model was trained on (a
slower servo, a softer column) needs no new model to be driven well, only the MPC told
how much later its commands act (``MpcTuning.delay_compensation_s``). That figure is
the difference of the two time constants, and the log of any drive holds it: the command
and the measured wheel angle are both on the bus.

The lag, discretised at the control period ``ts`` with the command held between steps::

    delta[k+1] = delta[k] + (1 - a) (u[k] - delta[k]),   a = exp(-ts / tau)

Steps where the wheel angle moves at the actuator's rate limit are left out: there the
servo is not a lag, and they would bias tau upwards.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.errors import ModelError


@dataclass(frozen=True)
class ServoFit:
    """Result of :func:`fit_servo_lag`: ``time_constant_s`` (s), the steps used, and the
    RMSE (rad) of the one-step prediction of the wheel angle on them."""

    time_constant_s: float
    steps: int
    one_step_rmse_rad: float


def fit_servo_lag(runs: Sequence[tuple[np.ndarray, np.ndarray]], ts: float,
                  rate_limit: float | None = None, min_steps: int = 200) -> ServoFit:
    """Fit the first-order lag of the wheel angle behind the command.

    Args:
        runs: per run, ``(steer_command, steer_measured)``, each (n,) rad, at the control
            instants (the command sent at instant k, the wheel angle sampled at k).
        ts: the control period (s).
        rate_limit: the actuator's steering rate limit (rad/s); steps whose wheel angle
            moves at 95 % of it or more are left out. None: none left out.
        min_steps: fewer usable steps than this is an error.

    Raises:
        ModelError: too few usable steps, or data that show no lag in (0, inf).
    """
    gaps, moves = [], []
    for command, measured in runs:
        command = np.asarray(command, dtype=float)
        measured = np.asarray(measured, dtype=float)
        if command.shape != measured.shape or command.ndim != 1:
            raise ModelError(f"servo fit: command {command.shape} and wheel angle {measured.shape} "
                             "must be equal 1-d arrays")
        move = np.diff(measured)
        gap = command[:-1] - measured[:-1]
        keep = np.isfinite(move) & np.isfinite(gap)
        if rate_limit is not None:
            keep &= np.abs(move) < 0.95 * rate_limit * ts
        gaps.append(gap[keep])
        moves.append(move[keep])
    gap = np.concatenate(gaps) if gaps else np.zeros(0)
    move = np.concatenate(moves) if moves else np.zeros(0)
    if gap.size < min_steps:
        raise ModelError(f"servo fit: {gap.size} usable steps, at least {min_steps} needed")
    energy = float(gap @ gap)
    if energy <= 0.0:
        raise ModelError("servo fit: the command never differs from the wheel angle")
    fraction = float(gap @ move) / energy          # 1 - a
    if not 0.0 < fraction < 1.0:
        raise ModelError(f"servo fit: the data give a step fraction of {fraction:.3f}, not a lag "
                         "(it must lie in (0, 1))")
    residual = move - fraction * gap
    return ServoFit(time_constant_s=-ts / math.log(1.0 - fraction), steps=int(gap.size),
                    one_step_rmse_rad=float(np.sqrt(np.mean(residual ** 2))))

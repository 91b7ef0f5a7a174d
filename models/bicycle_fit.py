"""A linear bicycle fitted to recorded data: cornering stiffnesses and yaw inertia.

LMPC's model (``models.bicycle.LinearBicycle``) with its three uncertain parameters
identified from a drive, the geometry (lf, lr) and the mass from a vehicle file (they are
weighed and measured, not identified). With the slip angles of the linear model,

    alpha_f = delta - (vy + lf r) / vx,      alpha_r = -(vy - lr r) / vx,

the lateral balance m (dvy/dt + vx r) = Cf alpha_f + Cr alpha_r is linear in (Cf, Cr):
least squares over every sample of the linear range; then the yaw balance
dr/dt = (lf Cf alpha_f - lr Cr alpha_r) / Iz gives 1/Iz by least squares (the regressor,
built from the measured angles, is far less noisy than the differentiated yaw rate, so it
is the regressor). Derivatives are forward differences over one Ts inside each piece,
against the mean of the regressors at its two ends; ``delta`` is the measured front wheel
angle where the data have it (the actuator's lag is then not folded into the tyres), else
the command.

A fitted bicycle file is JSON (``kind = "linear_bicycle"``): the six parameters, the fit's
residuals and sample counts, and where the data came from. ``load_bicycle`` turns it into a
``LinearBicycle`` for LMPC (``python -m firmware_sim --controller lmpc --model FILE``).
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.bicycle import LinearBicycle, NominalModelParams, nominal_model_params
from models.errors import ModelError
from models.input_files import MODEL_FILE_MAX_BYTES, read_bounded
from models.koopman_metrics import Trajectory
from models.vehicle_params import load_vehicle_params

BICYCLE_FILE_KIND = "linear_bicycle"
BICYCLE_FILE_FORMAT = 1
#: Fitted and geometric fields of a bicycle file (SI units; stiffnesses per axle).
BICYCLE_FIELDS = ("mass", "yaw_inertia", "lf", "lr", "cornering_stiffness_front",
                  "cornering_stiffness_rear")
#: Samples used by the fit: fast enough for the 1/vx terms, inside the tyres' linear range
#: (slip angles of at most 0.04 rad: 2.3 degrees).
MIN_FIT_SPEED_MPS = 4.0
MAX_FIT_SLIP_RAD = 0.04


class BicycleFitError(ModelError):
    """A bicycle file is unusable or the data cannot identify the bicycle (names the file)."""


@dataclass(frozen=True)
class BicycleFit:
    """Result of `fit_bicycle`: the parameters and how well they explain the data."""

    params: NominalModelParams
    samples_used: int
    samples_total: int
    lateral_residual_rms_n: float
    yaw_residual_rms: float

    def as_dict(self) -> dict[str, Any]:
        """The bicycle file's content (without provenance)."""
        return {"kind": BICYCLE_FILE_KIND, "format": BICYCLE_FILE_FORMAT,
                **{name: float(getattr(self.params, name)) for name in BICYCLE_FIELDS},
                "fit": {"samples_used": self.samples_used, "samples_total": self.samples_total,
                        "lateral_residual_rms_n": self.lateral_residual_rms_n,
                        "yaw_accel_residual_rms_rad_s2": self.yaw_residual_rms,
                        "min_speed_mps": MIN_FIT_SPEED_MPS,
                        "max_slip_rad": MAX_FIT_SLIP_RAD}}


def _column(run: Trajectory, *names: str) -> np.ndarray | None:
    for name in names:
        if name in run.state_names:
            return run.states[:, run.state_names.index(name)]
        if name in run.input_names:
            return run.inputs[:, run.input_names.index(name)]
    return None


def _regressors(runs: Sequence[Trajectory], ts: float, lf: float, lr: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """Per usable step k -> k+1: slip angles (n, 2), lateral acceleration (n,), yaw
    acceleration (n,); the number of steps seen; and the steps themselves (n, 6):
    [mean vx, vy_k, r_k, mean wheel angle, vy_k+1, r_k+1]."""
    alphas, lateral, yaw_accel, steps = [], [], [], []
    total = 0
    for run in runs:
        vx, vy, r = (_column(run, name) for name in ("vx", "vy", "yaw_rate"))
        delta = _column(run, "steer_measured", "steer")
        if vx is None or vy is None or r is None or delta is None or len(run) < 2:
            continue
        total += len(run) - 1
        # Forward differences against the interval's mean regressors (trapezoidal rule):
        # exact for states that change linearly over Ts, and the measured wheel angle is
        # continuous (its actuator lags the command).
        dvy = (vy[1:] - vy[:-1]) / ts
        dr = (r[1:] - r[:-1]) / ts
        v, lat_v, rate, angle = ((c[1:] + c[:-1]) / 2.0 for c in (vx, vy, r, delta))
        speed = np.maximum(v, MIN_FIT_SPEED_MPS)
        accel = dvy + v * rate
        alpha_f = angle - (lat_v + lf * rate) / speed
        alpha_r = -(lat_v - lr * rate) / speed
        # Selected on the regressors (slip angles), never on the differentiated response:
        # a bound on that would bias the slopes towards zero.
        keep = ((v >= MIN_FIT_SPEED_MPS) & (np.abs(alpha_f) <= MAX_FIT_SLIP_RAD)
                & (np.abs(alpha_r) <= MAX_FIT_SLIP_RAD))
        alphas.append(np.column_stack([alpha_f, alpha_r])[keep])
        lateral.append(accel[keep])
        yaw_accel.append(dr[keep])
        steps.append(np.column_stack([v, vy[:-1], r[:-1], angle, vy[1:], r[1:]])[keep])
    if not alphas:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), total, np.zeros((0, 6))
    return (np.concatenate(alphas), np.concatenate(lateral), np.concatenate(yaw_accel), total,
            np.concatenate(steps))


def _one_step_residuals(params: NominalModelParams, steps: np.ndarray, ts: float,
                        scale: np.ndarray) -> np.ndarray:
    """Scaled one-step errors (2 n,) of the exactly discretised bicycle on ``steps``
    (rows [mean vx, vy_k, r_k, mean wheel angle, vy_k+1, r_k+1]); the speed in buckets of
    0.1 m/s (one matrix exponential per bucket)."""
    bicycle = LinearBicycle(params)
    buckets = np.round(steps[:, 0] / 0.1).astype(int)
    predicted = np.empty((len(steps), 2))
    for bucket in np.unique(buckets):
        rows = buckets == bucket
        a, b = bicycle.discrete_matrices(bucket * 0.1, ts)
        predicted[rows] = steps[rows, 1:3] @ a.T + np.outer(steps[rows, 3], b[:, 0])
    return ((steps[:, 4:6] - predicted) / scale).ravel()


def _refine(start: NominalModelParams, steps: np.ndarray, ts: float) -> NominalModelParams:
    """Cf, Cr, Iz minimising the one-step prediction error of the exactly discretised
    bicycle (the derivative regression is only first order in Ts: at 25 ms and lateral
    time constants of tens of ms it misses the stiffnesses by several per cent)."""
    from scipy.optimize import least_squares

    names = ("cornering_stiffness_front", "cornering_stiffness_rear", "yaw_inertia")
    scale = np.maximum(np.std(steps[:, 4:6] - steps[:, 1:3], axis=0), 1e-9)

    def residuals(log_values: np.ndarray) -> np.ndarray:
        values = dict(zip(names, np.exp(log_values)))
        return _one_step_residuals(dataclasses.replace(start, **values), steps, ts, scale)

    solution = least_squares(residuals, np.log([getattr(start, n) for n in names]), x_scale=1.0,
                             diff_step=1e-4, max_nfev=60)
    return dataclasses.replace(start, **dict(zip(names, np.exp(solution.x))))


def fit_bicycle(runs: Sequence[Trajectory], ts: float, vehicle_file: str | Path | None = None,
                min_samples: int = 400) -> BicycleFit:
    """Fit Cf, Cr (N/rad per axle) and Iz (kg m^2) to ``runs`` (states with vx, vy,
    yaw_rate; the wheel angle as ``steer_measured`` or the input ``steer``).

    Mass and geometry come from ``vehicle_file`` (default ``models/vehicle.toml``).

    Raises:
        BicycleFitError: too few samples in the linear range, or a fit that is not
            physical (a stiffness or inertia <= 0: the data do not excite the lateral
            dynamics).
    """
    nominal = nominal_model_params(load_vehicle_params(vehicle_file) if vehicle_file else None)
    alphas, lateral, yaw_accel, total, steps = _regressors(runs, ts, nominal.lf, nominal.lr)
    if len(lateral) < min_samples:
        raise BicycleFitError(f"bicycle fit: {len(lateral)} samples above {MIN_FIT_SPEED_MPS} m/s in "
                              f"the linear range (slip angles <= {MAX_FIT_SLIP_RAD} rad), "
                              f"need {min_samples}")
    force = nominal.mass * lateral
    stiffness, *_ = np.linalg.lstsq(alphas, force, rcond=None)
    cf, cr = (float(v) for v in stiffness)
    moment = nominal.lf * cf * alphas[:, 0] - nominal.lr * cr * alphas[:, 1]
    denominator = float(moment @ moment)
    inverse_inertia = float(moment @ yaw_accel) / denominator if denominator > 0 else math.nan
    if not (cf > 0 and cr > 0 and inverse_inertia > 0 and math.isfinite(inverse_inertia)):
        raise BicycleFitError(f"bicycle fit is not physical (Cf {cf:.0f} N/rad, Cr {cr:.0f} N/rad, "
                              f"1/Iz {inverse_inertia:.3g}): the data do not excite the lateral "
                              "dynamics (drive with --excite)")
    params = _refine(dataclasses.replace(nominal, yaw_inertia=1.0 / inverse_inertia,
                                         cornering_stiffness_front=cf, cornering_stiffness_rear=cr),
                     steps, ts)
    stiffness = np.array([params.cornering_stiffness_front, params.cornering_stiffness_rear])
    moment = nominal.lf * stiffness[0] * alphas[:, 0] - nominal.lr * stiffness[1] * alphas[:, 1]
    inverse_inertia = 1.0 / params.yaw_inertia
    return BicycleFit(
        params=params, samples_used=int(len(lateral)), samples_total=int(total),
        lateral_residual_rms_n=float(np.sqrt(np.mean((alphas @ stiffness - force) ** 2))),
        yaw_residual_rms=float(np.sqrt(np.mean((moment * inverse_inertia - yaw_accel) ** 2))))


def save_bicycle(path: str | Path, fit: BicycleFit, provenance: dict[str, Any]) -> Path:
    """Write the bicycle file (JSON) with ``provenance`` (logs, vehicle file, ...)."""
    path = Path(path)
    path.write_text(json.dumps({**fit.as_dict(), "provenance": provenance}, indent=1) + "\n")
    return path


def load_bicycle_params(path: str | Path) -> NominalModelParams:
    """A bicycle file's parameters over the nominal ones (the nonlinear fields, which LMPC
    does not use, stay nominal).

    Raises:
        BicycleFitError: unreadable, not a bicycle file, or a field missing / not a
            positive finite number (the message names the file and the field).
    """
    path = Path(path)
    try:
        content = json.loads(read_bounded(path, MODEL_FILE_MAX_BYTES, BicycleFitError))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise BicycleFitError(f"{path}: not a readable JSON bicycle file: {error}") from error
    if not isinstance(content, dict) or content.get("kind") != BICYCLE_FILE_KIND:
        kind = content.get("kind") if isinstance(content, dict) else type(content).__name__
        raise BicycleFitError(f"{path}: kind {kind!r} is not {BICYCLE_FILE_KIND!r} "
                              "(a fitted bicycle file of python -m models.koopman_train --logs)")
    values = {}
    for name in BICYCLE_FIELDS:
        value = content.get(name)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) \
                or value <= 0:
            raise BicycleFitError(f"{path}: field {name} must be a positive number, got {value!r}")
        values[name] = float(value)
    return dataclasses.replace(nominal_model_params(), **values)


def load_bicycle(path: str | Path) -> LinearBicycle:
    """The fitted bicycle of a file, ready for LMPC."""
    return LinearBicycle(load_bicycle_params(path))


class FittedBicyclePredictor:
    """A bicycle as a Table I predictor: speed held at its start value, input ``steer``
    (the input column the bicycle's delta is), states [vx, vy, yaw_rate] predicted."""

    def __init__(self, bicycle: LinearBicycle, ts: float, steer_index: int = 1) -> None:
        self.bicycle, self.ts, self.steer_index = bicycle, ts, steer_index
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _matrices(self, vx: float) -> tuple[np.ndarray, np.ndarray]:
        key = round(max(vx, 1.0) / 0.05)  # 0.05 m/s buckets: far below the model's error
        if key not in self._cache:
            a, b = self.bicycle.discrete_matrices(key * 0.05, self.ts)
            self._cache[key] = (a, np.asarray(b).reshape(2))
        return self._cache[key]

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, >= 3), inputs (batch, n, n_u) -> states (batch, n, 3)."""
        out = np.empty(inputs.shape[:2] + (3,))
        for b in range(len(x0)):
            a, gain = self._matrices(float(x0[b, 0]))
            lateral = np.array(x0[b, 1:3], dtype=float)
            for i in range(inputs.shape[1]):
                lateral = a @ lateral + gain * inputs[b, i, self.steer_index]
                out[b, i, 1:] = lateral
            out[b, :, 0] = x0[b, 0]
        return out

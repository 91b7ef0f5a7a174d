"""Local linear fits of the lateral dynamics on a speed band of recorded runs (numpy).

At a speed v, one-step least squares (Table I's ``DMDc``) on the samples of the runs within
+-``BAND`` m/s of v that a mask selects gives a local linear model of the lateral states and
the wheel angle,

    [vy, r, delta]_(k+1) = A [vy, r, delta]_k + B [torque, steer]_k + c.

On gentle samples (well inside the friction circle) such a fit holds the vehicle's
small-signal response at that speed (``make lateral-regimes``). Used by the lateral-regimes
study and by the training's gain anchor (``models/koopman_train_anchor.py``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.errors import DatasetError
from models.koopman_baselines import DMDc
from models.koopman_metrics import Trajectory

GRAVITY = 9.81
#: Half-width (m/s) of the speed band whose samples a local fit uses.
BAND = 0.7
#: Fewest samples a fit needs (3 states + 2 inputs + 1 constant regressors, with margin).
MIN_SAMPLES = 200
#: Ridge of the fits (``DMDc``, standardised columns): only keeps a regime without torque solvable.
RIDGE = 1e-10
LATERAL = ("vy", "yaw_rate", "steer_measured")
STATES = ("vx", *LATERAL)
INPUTS = ("torque", "steer")


@dataclass(frozen=True)
class SampleSignals:
    """Per-sample signals of one run that the regimes select on (each (n,))."""

    ax: np.ndarray
    lateral_grip: np.ndarray
    combined_grip: np.ndarray


#: Sample time (s) of the data the fits are made on (the ECU's control period).
TS = 0.025


def single_track_yaw_rate(step: float, length: float, understeer: float,
                          speed: float | np.ndarray) -> float | np.ndarray:
    """Steady-state yaw rate (rad/s) of a linear single track after a steer step ``step``
    (rad) at ``speed`` (m/s; scalar or any shape): step v / (L + K v^2), with ``length`` L
    (m) and ``understeer`` K (s^2/m). The gain anchor's smoothing (models/koopman_train_anchor.py)."""
    v = np.asarray(speed, dtype=float)
    return step * v / (length + understeer * v ** 2)


def signals(run: Trajectory, mu: float) -> SampleSignals:
    """ax (central difference of vx, m/s^2) and the grip use of a run on friction ``mu``."""
    vx = run.states[:, run.state_names.index("vx")]
    lateral = vx * run.states[:, run.state_names.index("yaw_rate")]
    ax = np.gradient(vx, TS)
    return SampleSignals(ax, np.abs(lateral) / (mu * GRAVITY), np.hypot(ax, lateral) / (mu * GRAVITY))


def friction_of_runs(directory: str | Path) -> dict[str, float]:
    """Run name -> the road's mu, from the generator's ``manifest.json`` of a data set
    (``models.data``); {} when the data set has no manifest (recorded logs, other sources).

    Raises ``DatasetError`` for a manifest that is not JSON or lacks its run list."""
    manifest_path = Path(directory) / "manifest.json"
    if not manifest_path.is_file():
        return {}
    try:
        manifest = json.loads(manifest_path.read_text())
        default = manifest.get("params", {}).get("mu")
        friction = {}
        for entry in manifest["runs"]:
            mu = entry.get("mu", default)
            if entry.get("file") and mu is not None:  # runs without a file were dropped
                friction[Path(entry["file"]).stem] = float(mu)
        return friction
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise DatasetError(f"{manifest_path}: not a data set manifest with a run list ({e})") from e


def band_segments(runs: Sequence[Trajectory], masks: Sequence[np.ndarray], speed: float) -> list[Trajectory]:
    """The stretches of each run whose samples k have mask[k] and |vx_k - speed| < BAND, each
    with the sample after it, on the lateral states: the one-step pairs (k, k + 1) of a fit.

    ``runs`` carry STATES and INPUTS; ``masks`` one (n,) bool per run."""
    segments = []
    for run, mask in zip(runs, masks):
        take = np.zeros(len(run), dtype=bool)  # the last sample has no successor
        take[:-1] = mask[:-1] & (np.abs(run.states[:-1, 0] - speed) < BAND)
        edges = np.flatnonzero(np.diff(np.r_[0, take.astype(int), 0]))
        for start, stop in zip(edges[::2], edges[1::2]):
            segments.append(Trajectory(f"{run.name}[{start}:{stop + 1}]", run.states[start:stop + 1, 1:],
                                       run.inputs[start:stop + 1], LATERAL, INPUTS))
    return segments


def local_fit(runs: Sequence[Trajectory], masks: Sequence[np.ndarray], speed: float) -> tuple[DMDc | None, int]:
    """DMDc, [vy, r, delta]+ = A [vy, r, delta] + B [torque, steer] + c, fitted on the
    ``band_segments``. Returns (the fit, number of one-step pairs); (None, n) when
    n < MIN_SAMPLES."""
    segments = band_segments(runs, masks, speed)
    n = sum(len(segment) - 1 for segment in segments)
    if n < MIN_SAMPLES:
        return None, n
    return DMDc(ridge=RIDGE).fit(segments), n


def antisymmetric_final(model: Any, start: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """The linear part of a model's steer response: (final(+steer) - final(-steer)) / 2.

    ``model.predict`` maps x0 (batch, n_x) and inputs (batch, n, 2) [torque, steer] to
    (batch, n, n_x); ``start`` (n_x,), ``commands`` (n, 2); the -steer run is ``commands``
    with the steer negated. Returns the state after the last step, (n_x,)."""
    mirrored = commands.copy()
    mirrored[:, 1] *= -1.0
    finals = [model.predict(np.asarray(start, dtype=float)[None], c[None])[0, -1] for c in (commands, mirrored)]
    return (finals[0] - finals[1]) / 2.0


class LocalLateralModel:
    """A local fit as a predictor for ``step_steer_final``: vx held, [vy, r, delta] by the fit."""

    n_x = 4

    def __init__(self, lateral: DMDc) -> None:
        self.lateral = lateral

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, 4) [vx, vy, r, delta], inputs (batch, n, 2) -> (batch, n, 4)."""
        x0 = np.asarray(x0, dtype=float)
        out = np.empty(inputs.shape[:2] + (4,))
        out[..., 0] = x0[:, :1]
        out[..., 1:] = self.lateral.predict(x0[:, 1:], inputs)
        return out



"""Gain anchor: hold the learned model's small-signal steer gain to the training data's
(build time only; the targets in numpy, the loss term in torch).

Why: the prediction loss leaves the response to a small steer change from straight driving
loosely set. Models whose validation loss differs by a few % differ by 5-10 points in their
step-steer yaw rate at one speed, and both the weights' draw and the train / validation
split move it (docs/koopman.md, "The steer-bilinear term"). The training runs themselves
hold that response: local linear fits on their gentle samples give the plant's step-steer
yaw rate within a few % (``make lateral-regimes``).

Targets (``anchor_targets``, from the training runs only, never the plant): at each of
``ANCHOR_SPEEDS``, a local fit (``models.local_lateral_fit``) on the samples of the speed
band whose combined acceleration hypot(ax, vx r) is below ``GENTLE_ACCEL``, driven from
straight driving by a step of +-``ANCHOR_STEP`` rad for ``ANCHOR_STEPS`` steps with the
band's median torque. The antisymmetric yaw rate at the end, half the difference of the two
signs, is the target. A fit is one draw from a few hundred samples, so the targets are
smoothed over speed by a polynomial of degree ``SMOOTH_DEGREE`` (weighted by the sample
counts); speeds with fewer than ``MIN_SAMPLES`` samples are left out.

Loss (``GainAnchor.loss``): the mean over the speeds of ((r_model - r_target) / r_target)^2,
r_model the learned model's antisymmetric yaw rate to the same steps (the scheduled form's
matrices of that speed, held), weighted by ``TrainingSettings.gain_anchor`` and added to
the training loss. Validation and early stopping keep the plain prediction loss.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from models.koopman import KoopmanError, MinMaxScaling, knot_weights
from models.koopman_metrics import Trajectory
from models.local_lateral_fit import (GRAVITY, INPUTS, MIN_SAMPLES, STATES, LocalLateralModel, band_segments,
                                      local_fit, signals)

#: Speeds (m/s) of the anchor: every 2 m/s over the training data's range.
ANCHOR_SPEEDS = tuple(float(v) for v in range(6, 32, 2))
#: Gentle samples: combined acceleration below this (m/s^2; 0.1 g, the tyres' linear range
#: on dry roads and a third of the grip at mu 0.3). Absolute, so that runs without a known
#: friction (CAN logs) can be anchored too.
GENTLE_ACCEL = 0.1 * GRAVITY
ANCHOR_STEP = 0.02  # rad, the step-steer study's
ANCHOR_STEPS = 40  # 1 s at 25 ms
SMOOTH_DEGREE = 3


@dataclass(frozen=True)
class AnchorTargets:
    """Per anchored speed: speed (m/s), the band's median torque (N m), the smoothed target
    yaw rate (rad/s), the local fit's own (unsmoothed) yaw rate, and its sample count;
    arrays of shape (n_speeds,)."""

    speeds: np.ndarray
    torques: np.ndarray
    yaw_rates: np.ndarray
    fitted_yaw_rates: np.ndarray
    samples: np.ndarray

    def as_json(self) -> dict[str, list[float]]:
        return {name: [round(float(v), 6) for v in getattr(self, name)]
                for name in ("speeds", "torques", "yaw_rates", "fitted_yaw_rates", "samples")}


def _on_fit_columns(run: Trajectory) -> Trajectory:
    """The run on the local fits' STATES and INPUTS (KoopmanError naming a missing column)."""
    missing = [n for n in STATES if n not in run.state_names] + [n for n in INPUTS if n not in run.input_names]
    if missing:
        raise KoopmanError(f"gain anchor: run {run.name} lacks {missing} (needs states {STATES}, inputs {INPUTS})")
    states = run.states[:, [run.state_names.index(n) for n in STATES]]
    inputs = run.inputs[:, [run.input_names.index(n) for n in INPUTS]]
    return Trajectory(run.name, states, inputs, STATES, INPUTS)


def anchor_targets(train_runs: Sequence[Trajectory], speeds: Sequence[float] = ANCHOR_SPEEDS) -> AnchorTargets:
    """The targets from the training runs (see the module docstring)."""
    runs = [_on_fit_columns(run) for run in train_runs]
    # grip use with mu = 1 is the combined acceleration in g
    masks = [signals(run, 1.0).combined_grip * GRAVITY < GENTLE_ACCEL for run in runs]
    rows = []
    for speed in speeds:
        fit, n = local_fit(runs, masks, speed)
        if fit is None:
            continue
        torque = float(np.median(np.concatenate([s.inputs[:, 0] for s in band_segments(runs, masks, speed)])))
        commands = np.zeros((2, ANCHOR_STEPS, 2))
        commands[..., 0] = torque
        commands[0, :, 1], commands[1, :, 1] = ANCHOR_STEP, -ANCHOR_STEP
        final = LocalLateralModel(fit).predict(np.tile([speed, 0.0, 0.0, 0.0], (2, 1)), commands)[:, -1, 2]
        rows.append((speed, torque, (final[0] - final[1]) / 2.0, n))
    if len(rows) < SMOOTH_DEGREE + 2:
        raise KoopmanError(f"gain anchor: only {len(rows)} of the speeds {tuple(speeds)} have {MIN_SAMPLES} gentle "
                           f"samples (combined acceleration < {GENTLE_ACCEL:.2f} m/s^2); need {SMOOTH_DEGREE + 2}")
    v, torque, fitted, n = (np.array(column, dtype=float) for column in zip(*rows))
    smooth = np.polyval(np.polyfit(v, fitted, SMOOTH_DEGREE, w=np.sqrt(n)), v)
    return AnchorTargets(v, torque, smooth, fitted, n)


class GainAnchor:
    """The anchor's loss term for a scheduled network (``KoopmanNet`` or ``MirrorKoopmanNet``)
    in the normalised units of training."""

    def __init__(self, targets: AnchorTargets, state_scaling: MinMaxScaling, input_scaling: MinMaxScaling,
                 speed_knots: Sequence[float], device: torch.device) -> None:
        n = targets.speeds.size
        starts = np.c_[targets.speeds, np.zeros((n, state_scaling.low.size - 1))]  # straight driving
        commands = np.zeros((2 * n, ANCHOR_STEPS, input_scaling.low.size))
        commands[..., 0] = np.tile(targets.torques, 2)[:, None]
        commands[:n, :, 1], commands[n:, :, 1] = ANCHOR_STEP, -ANCHOR_STEP

        def tensor(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(a, dtype=torch.float32, device=device)

        self.starts_n = tensor(np.tile(state_scaling.normalise(starts), (2, 1)))  # (2n, n_x): +step, then -step
        self.commands_n = tensor(input_scaling.normalise(commands))  # (2n, steps, n_u)
        self.knot_weights = tensor(np.tile(knot_weights(np.asarray(speed_knots), targets.speeds), (2, 1)))
        self.targets = tensor(targets.yaw_rates)
        self.yaw_span = float(state_scaling.high[2] - state_scaling.low[2])  # rad/s per normalised unit
        self.n = n

    def loss(self, net: torch.nn.Module) -> torch.Tensor:
        """Mean squared relative error of the net's antisymmetric yaw rate (scalar)."""
        no_dictionary = torch.zeros(2 * self.n, 0, device=self.starts_n.device)
        z0 = net.lift(self.starts_n, no_dictionary)
        yaw = net.rollout(z0, self.commands_n, self.knot_weights)[:, -1, 2]
        antisymmetric = (yaw[: self.n] - yaw[self.n:]) / 2.0 * self.yaw_span
        return torch.mean(((antisymmetric - self.targets) / self.targets) ** 2)

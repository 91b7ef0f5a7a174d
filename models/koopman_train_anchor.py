"""Gain anchor: hold the learned model's small-signal steer gain to the training data's
(build time only; the targets in numpy, the loss term in torch).

Why: the prediction loss leaves the response to a small steer change from straight driving
loosely set. Models whose validation loss differs by a few % differ by 5-10 points in their
step-steer yaw rate at one speed, and both the weights' draw and the train / validation
split move it (docs/koopman.md, "The steer-bilinear term"). The training runs themselves
hold that response: local linear fits on their gentle samples give the plant's step-steer
yaw rate within a few % (``make lateral-regimes``).

Targets (``anchor_targets``, from the training runs only, never the plant): at each of
``ANCHOR_SPEEDS``, a local fit (``models.local_lateral_fit``) on the gentle samples of the
speed band, driven from straight driving by a step of +-``ANCHOR_STEP`` rad for
``ANCHOR_STEPS`` steps with the band's median torque. The antisymmetric yaw rate at the end,
half the difference of the two signs, is the fitted response. Gentle: combined grip use
hypot(ax, vx r) / (mu g) below ``GENTLE_GRIP``, with each run's mu where the data set states
it (the generator's manifest); a run without a known mu is taken as mu = 1 (0.1 g), which
on a slippery road admits samples beyond the tyres' linear range and biases its fits low.
A fit is one draw from a few hundred samples, so the fitted responses are smoothed over
speed by the steady-state yaw gain of a linear single track, r = step v / (L + K v^2): two
parameters (the wheelbase-like L and the understeer-like K), fitted by least squares on
step v / r weighted by sqrt(samples) and relative; speeds with fewer than ``MIN_SAMPLES``
samples are left out. Why this smoothing and these speeds: a cubic over 6-30 m/s followed
the 6 m/s fits, which scatter by tens of % (few gentle samples in a band where the data
mostly accelerate), and pulled 8-12 m/s off by up to 12 % (docs/koopman.md, "The gain
anchor").

Loss (``GainAnchor.loss``): the mean over the speeds of ((r_model - r_target) / r_target)^2,
r_model the learned model's antisymmetric yaw rate to the same steps (the scheduled form's
matrices of that speed, held), weighted by ``TrainingSettings.gain_anchor`` and added to
the training loss. Validation and early stopping keep the plain prediction loss.

The lateral velocity (``TrainingSettings.gain_anchor_vy``, off by default). Why: the yaw
term alone leaves the step-steer vy free, and the anchored default's is off by up to
0.12 m/s 1 s after the step (docs/koopman.md, "The lateral velocity"), although local fits
give the plant's. Fits at the step's amplitude: the vy after a steer step of ANCHOR_STEP
stops being linear in the step at speed (the plant's is 11-14 % larger in magnitude at
20-28 m/s than 8 x its response to a quarter of the step, the yaw rate within 1.2 %), so
the gentle samples' fit, which holds the small-signal response, gives a vy below the step's.
Each speed's vy therefore comes from a fit on the samples whose grip use stays below the
step's own (``vy_grip_limit``: the smoothed yaw target's v r / g, the step taken on a dry
road, and at least GENTLE_GRIP), the response that the step reaches, linearised over the
range it crosses; it is a superset of the gentle samples, so every anchored speed has one.
Targets (``lateral_velocity_targets``): those fits' vy after the same steps, smoothed over
speed through their ratio vy / r (each fit's own r), the distance behind the
centre of gravity of the point of the car's axis that moves without sideslip. For a linear
single track at steady state it is b - c v^2 (b the distance to the rear axle, c = m l_f /
(L C_r)), so vy_target = r_target (b - c v^2), with (b, c) fitted by least squares on the
fits' own vy / r weighted by sqrt(samples). The ratio and not vy itself, because vy
crosses zero (between 15 and 20 m/s for the plant) where a relative error has no meaning;
for the same reason the loss (``GainAnchor.losses``, "anchor_vy") is the mean over the
speeds of ((vy_model - vy_target) / (r_target x ``VY_LENGTH``))^2: the error of vy / r in
metres, so that an error of 0.1 m weighs like a 10 % error of the yaw rate. Its speeds are
every ``VY_SPEED_STEP`` m/s over the anchored range, not only the anchor's: both smoothed
curves are defined at any speed, and a first training on the anchor's even speeds alone
held vy there within 0.01 m of vy / r but left it 0.14 m off at the 15 m/s speed knot
between them (the knot's own matrices were free; 14 and 16 m/s blend them with the
neighbours'). The torque there is the anchor bands' median, interpolated over speed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch

from models.koopman import KoopmanError, MinMaxScaling, knot_weights
from models.koopman_dictionary import dictionary_features
from models.koopman_metrics import Trajectory
from models.local_lateral_fit import (GRAVITY, INPUTS, MIN_SAMPLES, STATES, LocalLateralModel,
                                      antisymmetric_final, band_segments, local_fit, signals,
                                      single_track_yaw_rate)

#: Speeds (m/s) of the anchor: every 2 m/s over the training data's range above 6 m/s.
ANCHOR_SPEEDS = tuple(float(v) for v in range(8, 32, 2))
#: Gentle samples: combined grip use hypot(ax, vx r) / (mu g) below this (the tyres' linear
#: range on every mu).
GENTLE_GRIP = 0.1
ANCHOR_STEP = 0.02  # rad, the step-steer study's
ANCHOR_STEPS = 40  # 1 s at 25 ms
#: Fewest anchored speeds for the two-parameter smoothing (with margin).
MIN_SPEEDS = 4
#: m: the lateral-velocity term's error is that of vy / r in units of this length (see above).
VY_LENGTH = 1.0
#: m/s: the lateral-velocity term's speeds, so that they include every speed knot (see above).
VY_SPEED_STEP = 1.0


@dataclass(frozen=True)
class AnchorTargets:
    """Per anchored speed: speed (m/s), the band's median torque (N m), the smoothed target
    yaw rate (rad/s), the local fit's own (unsmoothed) yaw rate, and its sample count;
    arrays of shape (n_speeds,). ``runs_with_friction``: how many of the training runs had a
    known mu (the others were taken as mu = 1). ``fitted_lateral_velocities`` (n_speeds,):
    vy (m/s) after the same steps of the fit at the step's amplitude (module docstring),
    ``lateral_fit_yaw_rates`` (n_speeds,) that fit's yaw rate (rad/s),
    ``lateral_grip_limits`` (n_speeds,) the grip use below which its samples lie and
    ``lateral_samples`` (n_speeds,) their count, for
    ``lateral_velocity_targets`` (None where not computed); not part of ``as_json``, whose
    record predates them."""

    speeds: np.ndarray
    torques: np.ndarray
    yaw_rates: np.ndarray
    fitted_yaw_rates: np.ndarray
    samples: np.ndarray
    single_track: tuple[float, float] = (0.0, 0.0)
    runs_with_friction: int = 0
    fitted_lateral_velocities: np.ndarray | None = None
    lateral_fit_yaw_rates: np.ndarray | None = None
    lateral_grip_limits: np.ndarray | None = None
    lateral_samples: np.ndarray | None = None

    def yaw_rate_at(self, speed: float | np.ndarray) -> float | np.ndarray:
        """The smoothed target at any ``speed`` (m/s): ANCHOR_STEP v / (L + K v^2)."""
        return single_track_yaw_rate(ANCHOR_STEP, *self.single_track, speed)

    def as_json(self) -> dict[str, list[float] | int]:
        out: dict[str, list[float] | int] = {
            name: [round(float(v), 6) for v in getattr(self, name)]
            for name in ("speeds", "torques", "yaw_rates", "fitted_yaw_rates", "samples")}
        out["single_track"] = [float(v) for v in self.single_track]  # L, K: step v / (L + K v^2)
        out["step"] = ANCHOR_STEP
        out["runs_with_friction"] = self.runs_with_friction
        return out


def _on_fit_columns(run: Trajectory) -> Trajectory:
    """The run on the local fits' STATES and INPUTS (KoopmanError naming a missing column)."""
    missing = [n for n in STATES if n not in run.state_names] + [n for n in INPUTS if n not in run.input_names]
    if missing:
        raise KoopmanError(f"gain anchor: run {run.name} lacks {missing} (needs states {STATES}, inputs {INPUTS})")
    states = run.states[:, [run.state_names.index(n) for n in STATES]]
    inputs = run.inputs[:, [run.input_names.index(n) for n in INPUTS]]
    return Trajectory(run.name, states, inputs, STATES, INPUTS)


def single_track_gain_fit(speeds: np.ndarray, yaw_rates: np.ndarray, weights: np.ndarray,
                          step: float = ANCHOR_STEP) -> np.ndarray:
    """(L, K) of r = step v / (L + K v^2) fitted to ``yaw_rates`` at ``speeds`` (each (n,);
    ``weights`` (n,) >= 0): weighted least squares on step v / r, each row divided by its
    value so that the residuals are relative. Raises KoopmanError for a non-positive response
    (the fit's form has none) or a fit without a positive L."""
    if np.any(yaw_rates <= 0.0):
        raise KoopmanError(f"gain anchor: a local fit turns the wrong way or not at all at "
                           f"{speeds[yaw_rates <= 0.0].tolist()} m/s (yaw rates {yaw_rates.round(4).tolist()})")
    target = step * speeds / yaw_rates
    w = weights / target
    coefficients, *_ = np.linalg.lstsq(np.c_[np.ones_like(speeds), speeds ** 2] * w[:, None], target * w, rcond=None)
    if coefficients[0] <= 0.0:
        raise KoopmanError(f"gain anchor: the single-track smoothing has no positive L ({coefficients.tolist()})")
    return coefficients


def anchor_targets(train_runs: Sequence[Trajectory], friction: Mapping[str, float] | None = None,
                   speeds: Sequence[float] = ANCHOR_SPEEDS) -> AnchorTargets:
    """The targets from the training runs (see the module docstring); ``friction``: run name
    -> mu where known (``models.dataset.friction_of_runs``)."""
    friction = friction or {}
    runs = [_on_fit_columns(run) for run in train_runs]
    grip_use = [signals(run, friction.get(run.name, 1.0)).combined_grip for run in runs]
    masks = [use < GENTLE_GRIP for use in grip_use]
    rows = []
    for speed in speeds:
        fit, n = local_fit(runs, masks, speed)
        if fit is None:
            continue
        torque = float(np.median(np.concatenate([s.inputs[:, 0] for s in band_segments(runs, masks, speed)])))
        final = anchor_step_response(fit, speed, torque)
        rows.append((speed, torque, final[2], n))
    if len(rows) < MIN_SPEEDS:
        raise KoopmanError(f"gain anchor: only {len(rows)} of the speeds {tuple(speeds)} have {MIN_SAMPLES} gentle "
                           f"samples (combined grip use < {GENTLE_GRIP}); need {MIN_SPEEDS}")
    v, torque, fitted, n = (np.array(column, dtype=float) for column in zip(*rows))
    length, understeer = single_track_gain_fit(v, fitted, np.sqrt(n))
    yaw_rates = single_track_yaw_rate(ANCHOR_STEP, length, understeer, v)
    limits = vy_grip_limit(v, yaw_rates)
    lateral = []
    for speed, band_torque, limit in zip(v, torque, limits):
        # a superset of the gentle samples (limit >= GENTLE_GRIP), so the fit exists
        fit, samples = local_fit(runs, [use < limit for use in grip_use], float(speed))
        lateral.append((*anchor_step_response(fit, float(speed), float(band_torque))[1:3], samples))
    fitted_vy, lateral_yaw, lateral_n = (np.array(column, dtype=float) for column in zip(*lateral))
    return AnchorTargets(v, torque, yaw_rates, fitted, n, (float(length), float(understeer)),
                         sum(run.name in friction for run in runs), fitted_vy, lateral_yaw, limits, lateral_n)


def vy_grip_limit(speeds: np.ndarray, yaw_rates: np.ndarray) -> np.ndarray:
    """The grip use below which the lateral velocity's fit takes its samples (each (n,)):
    the steady lateral acceleration v r / g of the step's smoothed yaw-rate target on a dry
    road (mu = 1), and at least GENTLE_GRIP (module docstring)."""
    return np.maximum(GENTLE_GRIP, np.asarray(speeds) * np.asarray(yaw_rates) / GRAVITY)


def anchor_step_response(fit: object, speed: float, torque: float) -> np.ndarray:
    """[vx, vy, r, delta] (4,): the antisymmetric state of a local ``fit`` ANCHOR_STEPS after a
    steer step of ANCHOR_STEP from straight driving at ``speed`` with ``torque`` held."""
    commands = np.zeros((ANCHOR_STEPS, 2))
    commands[:, 0], commands[:, 1] = torque, ANCHOR_STEP
    return antisymmetric_final(LocalLateralModel(fit), np.array([speed, 0.0, 0.0, 0.0]), commands)


@dataclass(frozen=True)
class LateralVelocityTargets:
    """The lateral-velocity term's targets, every VY_SPEED_STEP over the anchored range (each
    (n_points,)): speed (m/s), torque (N m), the smoothed target yaw rate (rad/s, the
    scale of the error) and vy (m/s); the local fits' own vy at the yaw anchor's speeds
    (``fitted_speeds``, ``fitted_lateral_velocities``, (n_speeds,)) and the grip use below
    which each fit's samples lie (``fitted_grip_limits``, (n_speeds,)); ``slip_free_point``
    (b, c) of the smoothing, vy / r = b - c v^2 (m, s^2/m; see the module docstring)."""

    speeds: np.ndarray
    torques: np.ndarray
    yaw_rates: np.ndarray
    lateral_velocities: np.ndarray
    fitted_speeds: np.ndarray
    fitted_lateral_velocities: np.ndarray
    fitted_grip_limits: np.ndarray
    slip_free_point: tuple[float, float]

    def as_json(self) -> dict[str, list[float] | float]:
        out: dict[str, list[float] | float] = {
            name: [round(float(v), 6) for v in getattr(self, name)]
            for name in ("speeds", "torques", "yaw_rates", "lateral_velocities", "fitted_speeds",
                         "fitted_lateral_velocities", "fitted_grip_limits")}
        out["slip_free_point"] = [float(v) for v in self.slip_free_point]  # b, c: vy / r = b - c v^2
        out["length"] = VY_LENGTH
        return out


def slip_free_distance(near: float, speed_factor: float, speed: float | np.ndarray) -> float | np.ndarray:
    """vy / r (m) of a linear single track at steady state at ``speed`` (m/s; any shape):
    b - c v^2, with ``near`` b (m) and ``speed_factor`` c (s^2/m)."""
    v = np.asarray(speed, dtype=float)
    return near - speed_factor * v ** 2


def slip_free_point_fit(speeds: np.ndarray, distances: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(b, c) of vy / r = b - c v^2 fitted to ``distances`` (vy / r, m) at ``speeds`` (each
    (n,); ``weights`` (n,) >= 0): weighted least squares with absolute residuals in metres
    (vy / r crosses zero, so relative ones would not do). Raises KoopmanError for a fit
    without positive b and c: a car's point without sideslip starts behind its centre of
    gravity and moves forward with speed, as its rear tyres take up slip."""
    coefficients, *_ = np.linalg.lstsq(np.c_[np.ones_like(speeds), -speeds ** 2] * weights[:, None],
                                       distances * weights, rcond=None)
    if np.any(coefficients <= 0.0):
        raise KoopmanError(f"gain anchor vy: vy / r of the local fits ({distances.round(3).tolist()} m at "
                           f"{speeds.tolist()} m/s) gives b - c v^2 without positive b and c ({coefficients.tolist()})")
    return coefficients


def lateral_velocity_targets(targets: AnchorTargets) -> LateralVelocityTargets:
    """The lateral-velocity targets from the yaw anchor's ``targets`` (``anchor_targets``):
    r_target (b - c v^2) every VY_SPEED_STEP over the anchored speeds, (b, c) fitted on the
    vy / r of the fits at the step's amplitude, weighted by sqrt(their samples)."""
    if (targets.fitted_lateral_velocities is None or targets.lateral_fit_yaw_rates is None
            or targets.lateral_samples is None):
        raise KoopmanError("gain anchor vy: the anchor targets carry no fitted lateral velocities")
    if np.any(targets.lateral_fit_yaw_rates <= 0.0):
        raise KoopmanError(f"gain anchor vy: a fit at the step's amplitude turns the wrong way or not at all at "
                           f"{targets.speeds[targets.lateral_fit_yaw_rates <= 0.0].tolist()} m/s")
    distances = targets.fitted_lateral_velocities / targets.lateral_fit_yaw_rates
    near, speed_factor = slip_free_point_fit(targets.speeds, distances, np.sqrt(targets.lateral_samples))
    speeds = np.arange(targets.speeds[0], targets.speeds[-1] + 1e-9, VY_SPEED_STEP)
    yaw_rates = np.asarray(targets.yaw_rate_at(speeds), dtype=float)
    return LateralVelocityTargets(speeds, np.interp(speeds, targets.speeds, targets.torques), yaw_rates,
                                  yaw_rates * slip_free_distance(near, speed_factor, speeds), targets.speeds,
                                  targets.fitted_lateral_velocities, targets.lateral_grip_limits,
                                  (float(near), float(speed_factor)))


class GainAnchor:
    """The anchor's loss terms for a scheduled network (``KoopmanNet`` or ``MirrorKoopmanNet``)
    in the normalised units of training: the yaw rate's, and the lateral velocity's where
    ``lateral_velocities`` are given."""

    def __init__(self, targets: AnchorTargets, state_scaling: MinMaxScaling, input_scaling: MinMaxScaling,
                 speed_knots: Sequence[float], device: torch.device, state_names: Sequence[str],
                 input_names: Sequence[str], lateral_velocities: LateralVelocityTargets | None = None,
                 dictionary: Sequence[str] = (), dictionary_scaling: MinMaxScaling | None = None) -> None:
        # The starts, vy and the yaw rate below are by position: the states must lead with these.
        if tuple(state_names[:3]) != ("vx", "vy", "yaw_rate") or tuple(input_names) != INPUTS:
            raise KoopmanError(f"gain anchor: needs states starting (vx, vy, yaw_rate) and inputs {INPUTS}, "
                               f"got {tuple(state_names)} and {tuple(input_names)}")
        self.device = device
        self.steps = _SteerSteps(targets.speeds, targets.torques, state_scaling, input_scaling, speed_knots, device,
                                 dictionary, dictionary_scaling)
        self.targets = self._tensor(targets.yaw_rates)
        self.yaw_span = float(state_scaling.high[2] - state_scaling.low[2])  # rad/s per normalised unit
        self.vy_span = float(state_scaling.high[1] - state_scaling.low[1])  # m/s per normalised unit
        self.vy_steps = None
        if lateral_velocities is not None:
            self.vy_steps = _SteerSteps(lateral_velocities.speeds, lateral_velocities.torques, state_scaling,
                                        input_scaling, speed_knots, device, dictionary, dictionary_scaling)
            self.lateral_velocities = self._tensor(lateral_velocities.lateral_velocities)
            # m/s: r_target x 1 m, never 0 (r_target > 0, single_track_gain_fit)
            self.vy_scale = self._tensor(lateral_velocities.yaw_rates * VY_LENGTH)

    def _tensor(self, a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=torch.float32, device=self.device)

    def loss(self, net: torch.nn.Module) -> torch.Tensor:
        """Mean squared relative error of the net's antisymmetric yaw rate (scalar)."""
        yaw = self.steps.antisymmetric_final(net)[:, 2] * self.yaw_span
        return torch.mean(((yaw - self.targets) / self.targets) ** 2)

    def losses(self, net: torch.nn.Module) -> dict[str, torch.Tensor]:
        """The terms (scalars): "anchor", ``loss``; with lateral velocity targets also
        "anchor_vy", the mean squared error of the net's antisymmetric vy over r_target x
        VY_LENGTH at the targets' speeds."""
        out = {"anchor": self.loss(net)}
        if self.vy_steps is not None:
            vy = self.vy_steps.antisymmetric_final(net)[:, 1] * self.vy_span
            out["anchor_vy"] = torch.mean(((vy - self.lateral_velocities) / self.vy_scale) ** 2)
        return out


class _SteerSteps:
    """Steps of +-ANCHOR_STEP rad for ANCHOR_STEPS steps from straight driving at ``speeds``
    with ``torques`` (each (n,)), in the normalised units of training."""

    def __init__(self, speeds: np.ndarray, torques: np.ndarray, state_scaling: MinMaxScaling,
                 input_scaling: MinMaxScaling, speed_knots: Sequence[float], device: torch.device,
                 dictionary: Sequence[str] = (), dictionary_scaling: MinMaxScaling | None = None) -> None:
        n = speeds.size
        starts = np.c_[speeds, np.zeros((n, state_scaling.low.size - 1))]  # straight driving
        # the lift's fixed dictionary of the starts (n, n_dict), normalised as in training
        features = (dictionary_scaling.normalise(dictionary_features(dictionary, starts)) if dictionary
                    else np.zeros((n, 0)))
        commands = np.zeros((2 * n, ANCHOR_STEPS, input_scaling.low.size))
        commands[..., 0] = np.tile(torques, 2)[:, None]
        commands[:n, :, 1], commands[n:, :, 1] = ANCHOR_STEP, -ANCHOR_STEP

        def tensor(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(a, dtype=torch.float32, device=device)

        self.starts_n = tensor(np.tile(state_scaling.normalise(starts), (2, 1)))  # (2n, n_x): +step, then -step
        self.dictionary_n = tensor(np.tile(features, (2, 1)))  # (2n, n_dict)
        self.commands_n = tensor(input_scaling.normalise(commands))  # (2n, steps, n_u)
        self.knot_weights = tensor(np.tile(knot_weights(np.asarray(speed_knots), speeds), (2, 1)))
        self.n = n

    def antisymmetric_final(self, net: torch.nn.Module) -> torch.Tensor:
        """Half the difference of the net's lifted states after the +step and the -step,
        (n, n_z), normalised units (the states lead)."""
        z0 = net.lift(self.starts_n, self.dictionary_n)
        final = net.rollout(z0, self.commands_n, self.knot_weights)[:, -1]  # (2n, n_z)
        return (final[: self.n] - final[self.n:]) / 2.0

"""Training of the deep Koopman model in torch (build time only; the ECU never imports this).

The network, its two forms (the paper's linear eq. 5 and the bilinear form that can give a
speed-dependent steering response) and the loss are in ``models/koopman_train_net.py``.
Everything is in min-max normalised units (bounds from the training runs only);
``models/koopman.py`` folds the normalisation into physical-unit matrices.

The sequence length p = 31 gives the MPC's own horizon (30 steps of 25 ms). (Eq. 10 as
printed re-lifts the true z_{k+i-1}; we roll out in the lifted space, as the MPC does.)
Validation is the weighted prediction loss over that horizon; the history also records
each state's horizon RMSE in physical units.

Optimiser: Adam with an exponential learning-rate decay per epoch (the paper says steepest
descent; Adam is our choice). Runs are split into train / validation / test BY RUN, never by
sample. Early stopping: an epoch counts as an improvement only when the validation loss
falls by more than ``min_delta`` (relative) below the best so far; training stops after
max(``patience``, a quarter of the best epoch) epochs without one and keeps the best
weights, so a run that ends by early stopping has converged (best epoch <= 0.8 x epochs
run). Deterministic for a
seed: ``torch.manual_seed``, ``use_deterministic_algorithms``, a fixed torch thread count
(``threads``, default 1: on the shared 2-core machine two torch threads ran 5x slower than
one, 2 it/s vs 9 it/s at load ~6), a seeded batch sampler, and a fixed number of steps per
epoch (never a wall-clock budget).

CLI: ``python -m models.koopman_train --data data/nominal --out models/artifacts/dk_d5``;
``--states/--inputs/--ts`` train on any named-column CSV data set; ``--logs LOG [LOG ...]
--out DIR`` trains from CAN logs of the contract's bus and writes the artefact, a fitted
bicycle and a report into DIR (``models/log_identification.py``, docs/identification.md).
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from models.koopman import (DEFAULT_SPEED_KNOTS, DICTIONARY, DICTIONARY_STATES, MODEL_FORMS, knot_weights, KoopmanError, KoopmanModel, MinMaxScaling, NormalisedKoopman,
                            check_dictionary, dictionary_features, save_artifact)
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors
from models.koopman_train_anchor import GainAnchor, anchor_targets
from models.koopman_train_net import KoopmanNet, least_squares_start
from models.koopman_train_symmetric import SERVO_INPUT, SERVO_STATE, MirrorKoopmanNet, parities, shared_servo_scaling
from models.local_lateral_fit import friction_of_runs

#: The measured front wheel angle (the steering actuator's state) joins the vehicle states:
#: with it the lift sees the tyres' slip angles and the actuator lag (docs/koopman.md).
DEFAULT_STATES = ("vx", "vy", "yaw_rate", "steer_measured")
DEFAULT_INPUTS = ("torque", "steer")


@dataclass(frozen=True)
class TrainingSettings:
    """Hyper-parameters of one training run (all stored in the artefact's JSON).

    ``seq_len`` is p of eq. 9: p states per sequence, p - 1 predicted steps (31: the MPC's
    horizon of 30). One epoch = ``steps_per_epoch`` Adam steps on batches drawn with
    replacement. ``form``: "linear" (the paper's eq. 5) or "bilinear"; ``dictionary``:
    fixed lifting functions (names of ``models.koopman.DICTIONARY``), () for none.

    Two options of the step-steer study (``studies.step_steer_spread``), off by default:
    ``small_signal_accel`` a0 > 0 weighs each window's prediction error by
    1 / (1 + (a / a0)^2), a the window's peak |vx r| (m/s^2), so windows in the tyres' linear
    range count more than those at the limit; ``unscheduled_states`` names states whose row
    of (A, B, c) is one for all speed knots (the wheel angle: the servo does not depend on
    speed). Both are left out of the artefact's settings record while off, so artefacts
    trained before them still match their settings.

    ``mirror_symmetric`` (scheduled form only) builds the left / right mirror symmetry into
    the model (``models/koopman_train_symmetric.py``): ``even_features`` of the d features
    are even, the rest odd; ``servo_lag`` makes the wheel-angle row a lag of unit DC gain
    from the steer command; ``lateral_per_step`` schedules the lateral rows on each step's
    measured speed in training; ``steer_bilinear`` adds a steer-bilinear term
    (u_steer - u0) N(v) (z - z0) whose N maps even to odd coordinates and back, so the
    response to a steer change depends on the state at a given speed. Recorded only when
    ``mirror_symmetric`` is on (``steer_bilinear`` only when on).

    ``gain_anchor`` w > 0 (scheduled form without dictionary; recorded only when on) adds
    w times the gain anchor's loss (``models/koopman_train_anchor.py``): the model's
    small-signal steer response held to local fits of the training runs' gentle samples.
    """

    n_features: int = 5
    hidden: tuple[int, ...] = (96, 96, 96)
    seq_len: int = 31
    batch_size: int = 128
    learning_rate: float = 2e-3
    lr_decay: float = 0.94
    max_epochs: int = 120
    steps_per_epoch: int = 100
    patience: int = 10
    min_delta: float = 0.005
    form: str = "scheduled"
    dictionary: tuple[str, ...] = ()
    speed_knots: tuple[float, ...] = DEFAULT_SPEED_KNOTS
    recon_weight: float = 1.0
    lifted_weight: float = 1.0
    small_signal_accel: float = 0.0
    unscheduled_states: tuple[str, ...] = ()
    mirror_symmetric: bool = False
    even_features: int = 2
    servo_lag: bool = False
    lateral_per_step: bool = False
    steer_bilinear: bool = False
    gain_anchor: float = 0.0
    val_fraction: float = 0.15
    test_fraction: float = 0.15
    val_windows: int = 4096
    seed: int = 0
    threads: int = 1
    warm_start: bool = True
    device: str = "auto"

    def __post_init__(self) -> None:
        checks = {
            "n_features": self.n_features >= 1,
            "hidden": len(self.hidden) >= 1 and all(h >= 1 for h in self.hidden),
            "seq_len": self.seq_len >= 2,
            "batch_size": self.batch_size >= 1,
            "learning_rate": self.learning_rate > 0,
            "lr_decay": 0 < self.lr_decay <= 1,
            "max_epochs": self.max_epochs >= 1,
            "steps_per_epoch": self.steps_per_epoch >= 1,
            "patience": self.patience >= 1,
            "min_delta": 0 <= self.min_delta < 1,
            "form": self.form in MODEL_FORMS,
            "speed_knots": len(self.speed_knots) >= 2 and all(b > a for a, b in zip(self.speed_knots, self.speed_knots[1:])),
            "dictionary": all(name in DICTIONARY for name in self.dictionary),
            "threads": self.threads >= 1,
            "recon_weight": self.recon_weight >= 0,
            "lifted_weight": self.lifted_weight >= 0,
            "small_signal_accel": self.small_signal_accel >= 0,
            "unscheduled_states": self.form == "scheduled" or not self.unscheduled_states,
            "mirror_symmetric": self.form == "scheduled" or not self.mirror_symmetric,
            "even_features": 0 <= self.even_features <= self.n_features,
            "servo_lag": self.mirror_symmetric or not self.servo_lag,
            "lateral_per_step": self.mirror_symmetric or not self.lateral_per_step,
            "steer_bilinear": self.mirror_symmetric or not self.steer_bilinear,
            "gain_anchor": self.gain_anchor >= 0 and (self.gain_anchor == 0 or (self.form == "scheduled"
                                                                                and not self.dictionary)),
            "val_fraction": 0 < self.val_fraction < 0.5,
            "test_fraction": 0 < self.test_fraction < 0.5,
            "device": self.device in ("auto", "cpu", "cuda"),
        }
        for name, ok in checks.items():
            if not ok:
                raise KoopmanError(f"training setting {name}={getattr(self, name)!r} is invalid")


@dataclass
class TrainingResult:
    """What ``train`` returns: the model (physical units), the split and the history."""

    model: KoopmanModel
    learned: NormalisedKoopman
    net: KoopmanNet
    train_runs: list[str]
    val_runs: list[str]
    test_runs: list[str]
    best_epoch: int
    best_val_loss: float
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0


# ---------------------------------------------------------------------- data handling
def split_runs(
    runs: Sequence[Trajectory], settings: TrainingSettings
) -> tuple[list[Trajectory], list[Trajectory], list[Trajectory]]:
    """Train / validation / test split by run (never by sample), shuffled by the seed."""
    if len(runs) < 3:
        raise KoopmanError(
            f"need at least 3 runs to split train / validation / test by run, got {len(runs)}"
        )
    ordered = sorted(runs, key=lambda r: r.name)
    order = np.random.default_rng(settings.seed).permutation(len(ordered))
    n_test = max(1, round(settings.test_fraction * len(runs)))
    n_val = max(1, round(settings.val_fraction * len(runs)))
    test = [ordered[i] for i in order[:n_test]]
    val = [ordered[i] for i in order[n_test : n_test + n_val]]
    train = [ordered[i] for i in order[n_test + n_val :]]
    return train, val, test


def fit_scaling(runs: Sequence[Trajectory]) -> tuple[MinMaxScaling, MinMaxScaling]:
    """Min-max bounds of states and inputs over the given (training) runs.

    A channel that never varies gets a unit span so that it normalises to 0 without a
    division by zero.
    """
    states = np.concatenate([r.states for r in runs])
    inputs = np.concatenate([r.inputs for r in runs])
    scalings = []
    for values in (states, inputs):
        low, high = values.min(axis=0), values.max(axis=0)
        high = np.where(high - low > 1e-9, high, low + 1.0)
        scalings.append(MinMaxScaling(low, high))
    return scalings[0], scalings[1]


def dictionary_scaling_of(runs: Sequence[Trajectory], dictionary: tuple[str, ...]) -> MinMaxScaling | None:
    """Min-max bounds of the dictionary features over the (training) runs; None without one."""
    if not dictionary:
        return None
    values = dictionary_features(dictionary, np.concatenate([r.states for r in runs]))
    low, high = values.min(axis=0), values.max(axis=0)
    return MinMaxScaling(low, np.where(high - low > 1e-9, high, low + 1.0))


def _known_coordinates(run: Trajectory, state_scaling: MinMaxScaling, dictionary: tuple[str, ...],
                       dictionary_scaling: MinMaxScaling | None) -> np.ndarray:
    """[x_n, psi_n] of one run, (n, n_x + n_dict)."""
    parts = [state_scaling.normalise(run.states)]
    if dictionary:
        parts.append(dictionary_scaling.normalise(dictionary_features(dictionary, run.states)))
    return np.hstack(parts)


class SequenceSet:
    """All length-p windows of a set of runs, gathered on the fly from one flat tensor.

    With a dictionary, its normalised features psi_n are computed once per sample here.
    """

    def __init__(
        self,
        runs: Sequence[Trajectory],
        seq_len: int,
        state_scaling: MinMaxScaling,
        input_scaling: MinMaxScaling,
        device: torch.device,
        role: str,
        dictionary: tuple[str, ...] = (),
        dictionary_scaling: MinMaxScaling | None = None,
        speed_knots: tuple[float, ...] = (),
    ) -> None:
        starts, offset = [], 0
        for run in runs:
            n_starts = len(run) - seq_len + 1
            if n_starts > 0:
                starts.append(offset + np.arange(n_starts))
            offset += len(run)
        if not starts:
            longest = max(len(r) for r in runs)
            raise KoopmanError(
                f"{role} runs are too short for sequences of length p={seq_len}: "
                f"the longest has {longest} samples"
            )
        states = np.concatenate([state_scaling.normalise(r.states) for r in runs])
        inputs = np.concatenate([input_scaling.normalise(r.inputs) for r in runs])
        psi = np.zeros((len(states), 0))
        if dictionary:
            psi = dictionary_scaling.normalise(
                dictionary_features(dictionary, np.concatenate([r.states for r in runs])))
        self.psi = torch.as_tensor(psi, dtype=torch.float32, device=device)
        weights = (knot_weights(np.array(speed_knots), np.concatenate([r.states[:, 0] for r in runs]))
                   if speed_knots else np.zeros((len(states), 0)))
        self.knot_weights = torch.as_tensor(weights, dtype=torch.float32, device=device)
        self.states = torch.as_tensor(states, dtype=torch.float32, device=device)
        self.inputs = torch.as_tensor(inputs, dtype=torch.float32, device=device)
        self.starts = torch.as_tensor(np.concatenate(starts), dtype=torch.long, device=device)
        self.offsets = torch.arange(seq_len, device=device)
        # |vx r| (m/s^2) per sample, the lateral acceleration of steady cornering; its peak over
        # each window (``peak_accel``) is worked out only when small-signal weighting asks.
        names = runs[0].state_names
        if "vx" in names and "yaw_rate" in names:
            self._lateral_accel = np.concatenate(
                [np.abs(r.states[:, names.index("vx")] * r.states[:, names.index("yaw_rate")]) for r in runs])
        else:
            self._lateral_accel = np.zeros(len(states))

    @functools.cached_property
    def peak_accel(self) -> torch.Tensor:
        """Peak |vx r| (m/s^2) over each window (n_windows,): how far into the tyres'
        nonlinear range the window goes (for ``window_weights``)."""
        rows = self.starts.cpu().numpy()[:, None] + np.arange(len(self.offsets))
        peak = self._lateral_accel[rows].max(axis=1)
        return torch.as_tensor(peak, dtype=torch.float32, device=self.states.device)

    def __len__(self) -> int:
        return int(self.starts.numel())

    def batch(self, which: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Window indices (b,) -> x_n (b, p, n_x), psi_n (b, p, n_dict), u_n (b, p - 1, n_u),
        knot weights of the first sample's speed (b, K) (K = 0 unless scheduled)."""
        rows = self.starts[which][:, None] + self.offsets
        return self.states[rows], self.psi[rows], self.inputs[rows[:, :-1]], self.knot_weights[rows[:, 0]]

    def step_knot_weights(self, which: torch.Tensor) -> torch.Tensor:
        """Window indices (b,) -> knot weights of the speed at the start of each step (b, p - 1, K)."""
        return self.knot_weights[self.starts[which][:, None] + self.offsets[:-1]]


# ---------------------------------------------------------------------- training
def pick_device(name: str) -> torch.device:
    """'auto' is CUDA when present, else CPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise KoopmanError("training setting device='cuda' but no CUDA device is available")
    return torch.device(name)


def seed_everything(seed: int, threads: int = 1) -> None:
    """Deterministic torch for this process.

    The thread count is part of the result (float32 sums split differently), so it is a
    recorded setting.
    """
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(threads)


def _total(losses: dict[str, torch.Tensor], settings: TrainingSettings) -> torch.Tensor:
    return (
        losses["prediction"]
        + settings.recon_weight * losses["reconstruction"]
        + settings.lifted_weight * losses["lifted"]
    )


def train(
    runs: Sequence[Trajectory],
    ts: float,
    settings: TrainingSettings = TrainingSettings(),
    progress: bool = True,
    metadata: dict | None = None,
    friction: Mapping[str, float] | None = None,
) -> TrainingResult:
    """Fit the deep Koopman model on ``runs`` (split by run) and return it in physical units.

    ``friction``: run name -> the road's mu where the data set states it
    (``models.dataset.friction_of_runs``); only the gain anchor uses it.

    The returned model's ``metadata`` holds everything the artefact JSON needs, including the
    test-run prediction errors of Table I.
    """
    started = time.perf_counter()
    if not runs:
        raise KoopmanError("no runs to train on")
    state_names, input_names = runs[0].state_names, runs[0].input_names
    for run in runs:
        if run.state_names != state_names or run.input_names != input_names:
            raise KoopmanError(f"run {run.name}: columns differ from run {runs[0].name}")
    seed_everything(settings.seed, settings.threads)
    device = pick_device(settings.device)
    missing = [name for name in settings.unscheduled_states if name not in state_names]
    if missing:
        raise KoopmanError(f"unscheduled_states {missing} are not among the states {state_names}")
    train_runs, val_runs, test_runs = split_runs(runs, settings)
    dictionary = check_dictionary(settings.dictionary, state_names)
    # The scheduled form schedules on the first state: the data's longitudinal speed.
    state_scaling, input_scaling = fit_scaling(train_runs)
    if settings.servo_lag:
        state_scaling, input_scaling = shared_servo_scaling(state_scaling, input_scaling, state_names, input_names)
    dictionary_scaling = dictionary_scaling_of(train_runs, dictionary)
    knots = settings.speed_knots if settings.form == "scheduled" else ()
    sets = [SequenceSet(group, settings.seq_len, state_scaling, input_scaling, device, role, dictionary,
                        dictionary_scaling, knots)
            for group, role in ((train_runs, "training"), (val_runs, "validation"))]
    train_set, val_set = sets
    # Errors in physical units over how far each state moves in a horizon (the std of
    # x_{k+p-1} - x_k over the training runs): vx, tens of m/s but slow, then weighs like
    # the quick lateral states. Weight = span / spread per state (normalised -> relative).
    horizon = settings.seq_len - 1
    spread = np.concatenate([r.states[horizon:] - r.states[:-horizon] for r in train_runs
                             if len(r) > horizon]).std(axis=0)
    span = state_scaling.high - state_scaling.low
    state_weights = torch.as_tensor(span / np.maximum(spread, 1e-6), dtype=torch.float32, device=device)
    # A fixed, evenly spread subset of validation windows keeps the check cheap and exact.
    val_index = torch.as_tensor(
        np.unique(np.linspace(0, len(val_set) - 1, min(settings.val_windows, len(val_set))).astype(int)),
        device=device,
    )

    bilinear = settings.form == "bilinear"
    shared_rows = [state_names.index(name) for name in settings.unscheduled_states]
    if settings.mirror_symmetric:
        net = MirrorKoopmanNet(
            len(state_names), len(input_names), settings.n_features, settings.hidden, len(knots),
            settings.even_features, parities(state_names), parities(dictionary), parities(input_names),
            state_scaling.shift, dictionary_scaling.shift if dictionary else np.zeros(0), input_scaling.shift,
            shared_rows, (state_names.index(SERVO_STATE), input_names.index(SERVO_INPUT)) if settings.servo_lag else None,
            _steer_input(input_names) if settings.steer_bilinear else None)
    else:
        net = KoopmanNet(len(state_names), len(input_names), settings.n_features, settings.hidden,
                         len(dictionary), bilinear, len(knots), shared_rows)
    if settings.warm_start:
        net.warm_start(least_squares_start(
            [_known_coordinates(r, state_scaling, dictionary, dictionary_scaling) for r in train_runs],
            [input_scaling.normalise(r.inputs) for r in train_runs], bilinear,
            knot_weights=[knot_weights(np.array(knots), r.states[:, 0]) for r in train_runs] if knots else None))
    net = net.to(device)
    anchor_targets_ = anchor_targets(train_runs, friction) if settings.gain_anchor > 0 else None
    anchor = (None if anchor_targets_ is None
              else GainAnchor(anchor_targets_, state_scaling, input_scaling, knots, device, state_names, input_names))
    optimiser = torch.optim.Adam(net.parameters(), lr=settings.learning_rate)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma=settings.lr_decay)
    sampler = torch.Generator(device="cpu").manual_seed(settings.seed)

    best_state = copy.deepcopy(net.state_dict())
    best_val, best_epoch, stale = math.inf, 0, 0
    history: list[dict[str, float]] = []
    bar = tqdm(
        total=settings.max_epochs * settings.steps_per_epoch,
        desc=f"deep Koopman d={settings.n_features}",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    for epoch in range(1, settings.max_epochs + 1):
        net.train()
        running = {"prediction": 0.0, "reconstruction": 0.0, "lifted": 0.0}
        if anchor is not None:
            running["anchor"] = 0.0
        for step in range(settings.steps_per_epoch):
            which = torch.randint(len(train_set), (settings.batch_size,), generator=sampler).to(device)
            x_n, psi_n, u_n, weights = train_set.batch(which)
            step_weights = train_set.step_knot_weights(which) if settings.lateral_per_step else None
            losses = net.losses(x_n, psi_n, u_n, state_weights, weights, step_weights)
            if settings.small_signal_accel > 0:
                window = window_weights(train_set.peak_accel[which], settings.small_signal_accel)
                # Normalised by the batch's mean weight: the loss keeps its scale.
                losses["prediction"] = (torch.mean(window[:, None, None] * losses["error"] ** 2)
                                        / torch.mean(window))
            if anchor is not None:  # a training term only: validation keeps the prediction loss
                losses["anchor"] = anchor.loss(net)
                losses["prediction"] = losses["prediction"] + settings.gain_anchor * losses["anchor"]
            loss = _total(losses, settings)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            for key in running:
                running[key] += losses[key].item() / settings.steps_per_epoch
            bar.update(1)
            if step % 25 == 0:
                bar.set_postfix(pred=f"{running['prediction'] * settings.steps_per_epoch / (step + 1):.2e}",
                                rec=f"{running['reconstruction'] * settings.steps_per_epoch / (step + 1):.2e}",
                                lift=f"{running['lifted'] * settings.steps_per_epoch / (step + 1):.2e}",
                                val=f"{best_val:.2e}", refresh=False)
        scheduler.step()
        val_loss, val_rmse = _validation(net, val_set, val_index, state_weights, span)
        history.append({"epoch": epoch, **running, "val": val_loss,
                        **{f"val_rmse_{name}": value for name, value in zip(state_names, val_rmse)}})
        if val_loss < best_val * (1.0 - settings.min_delta):
            best_val, best_epoch, stale = val_loss, epoch, 0
            best_state = copy.deepcopy(net.state_dict())
        else:
            stale += 1
            # Converged: no improvement for `patience` epochs and for a quarter of the
            # epochs the best took, so the best epoch is at most 0.8 of the epochs run.
            if stale >= max(settings.patience, math.ceil(0.25 * best_epoch)):
                bar.write(f"early stop after epoch {epoch}: best validation loss {best_val:.3e} at epoch {best_epoch}")
                break
    bar.close()
    net.load_state_dict(best_state)
    net.eval()

    learned = net.export(state_scaling, input_scaling, dictionary, dictionary_scaling, knots)
    meta = dict(metadata or {})
    meta.update(
        d=settings.n_features,
        ts=float(ts),
        state_names=list(state_names),
        input_names=list(input_names),
        seed=settings.seed,
        settings=settings_json(settings),
        optimiser="Adam (paper: steepest descent), exponential lr decay per epoch",
        split={"train": [r.name for r in train_runs], "validation": [r.name for r in val_runs],
               "test": [r.name for r in test_runs]},
        best_epoch=best_epoch,
        epochs_run=len(history),
        best_validation_loss=best_val,
        validation_horizon_rmse={name: history[best_epoch - 1][f"val_rmse_{name}"] for name in state_names},
        validation_horizon_steps=settings.seq_len - 1,
        history=[{key: round(value, 7) for key, value in row.items()} for row in history],
        torch_version=torch.__version__,
        device=str(device),
    )
    model = KoopmanModel.from_normalised(learned, ts, state_names, input_names, meta)
    meta["spectral_radius_A"] = model.spectral_radius()
    meta["test_errors"] = prediction_errors(model, test_runs, open_loop_steps=OPEN_LOOP_STEPS)
    meta["test_open_loop_steps"] = OPEN_LOOP_STEPS
    if anchor_targets_ is not None:
        meta["gain_anchor_targets"] = anchor_targets_.as_json()
    elapsed = time.perf_counter() - started
    meta["training_seconds"] = round(elapsed, 1)
    model.metadata = meta
    return TrainingResult(
        model=model, learned=learned, net=net,
        train_runs=[r.name for r in train_runs], val_runs=[r.name for r in val_runs],
        test_runs=[r.name for r in test_runs], best_epoch=best_epoch, best_val_loss=best_val,
        history=history, seconds=elapsed,
    )


def window_weights(peak_accel: torch.Tensor, small_signal_accel: float) -> torch.Tensor:
    """Weights (b,) of windows with peak |vx r| ``peak_accel`` (b,) in m/s^2:
    1 / (1 + (a / a0)^2), a0 = ``small_signal_accel``. The validation loss stays unweighted."""
    return 1.0 / (1.0 + (peak_accel / small_signal_accel) ** 2)


@torch.no_grad()
def _validation(net: KoopmanNet, val_set: SequenceSet, index: torch.Tensor, state_weights: torch.Tensor,
                span: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted prediction loss over the horizon and each state's horizon RMSE (physical units)."""
    net.eval()
    squared = torch.zeros(net.n_x, dtype=torch.float64)
    count = 0
    for chunk in torch.split(index, 1024):
        x_n, psi_n, u_n, weights = val_set.batch(chunk)
        error = net.losses(x_n, psi_n, u_n, state_weights, weights)["error"]
        squared += (error.double() ** 2).sum(dim=(0, 1))
        count += error.shape[0] * error.shape[1]
    mean_squared = squared.numpy() / count  # per state, weighted units
    rmse = np.sqrt(mean_squared) / state_weights.double().cpu().numpy() * span
    return float(mean_squared.mean()), rmse


def settings_json(settings: TrainingSettings) -> dict:
    out = asdict(settings)
    out["hidden"] = list(settings.hidden)
    out["dictionary"] = list(settings.dictionary)
    out["speed_knots"] = list(settings.speed_knots)
    out["unscheduled_states"] = list(settings.unscheduled_states)
    # Options added after artefacts were committed: recorded only when on (see the class).
    for name in ("small_signal_accel", "unscheduled_states"):
        if not out[name]:
            del out[name]
    if not settings.mirror_symmetric:
        for name in ("mirror_symmetric", "even_features", "servo_lag", "lateral_per_step"):
            del out[name]
    if not settings.steer_bilinear:
        del out["steer_bilinear"]
    if not settings.gain_anchor:
        del out["gain_anchor"]
    return out


def _steer_input(input_names: Sequence[str]) -> int:
    """Index of the steer command (the steer-bilinear term's input); KoopmanError without one."""
    if SERVO_INPUT not in input_names:
        raise KoopmanError(f"steer_bilinear needs {SERVO_INPUT!r} among the inputs {tuple(input_names)}")
    return list(input_names).index(SERVO_INPUT)


def write_artifact(result: TrainingResult, out: str | Path) -> tuple[Path, Path]:
    """Save a training result as ``<out>.npz`` + ``<out>.json``."""
    return save_artifact(out, result.learned, result.model.metadata)


# ---------------------------------------------------------------------- data sets
def dataset_hash(directory: str | Path) -> str:
    """Identity of a data set: the manifest's hash when it states one, else sha256 of the files.

    The generator's ``manifest.json`` is preferred so that the artefact names the data set the
    way the data set names itself; any other directory is hashed file by file (sorted names).
    """
    directory = Path(directory)
    manifest = directory / "manifest.json"
    if manifest.is_file():
        try:
            content = json.loads(manifest.read_text())
        except json.JSONDecodeError:
            content = {}
        for key in ("content_sha256", "data_hash", "sha256", "hash"):
            if isinstance(content, dict) and isinstance(content.get(key), str):
                return "sha256:" + content[key] if key == "content_sha256" else content[key]
        return "sha256:" + hashlib.sha256(manifest.read_bytes()).hexdigest()
    digest = hashlib.sha256()
    for path in sorted(directory.glob("*.csv")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return "sha256:" + digest.hexdigest()


def load_trajectories(
    directory: str | Path,
    states: Sequence[str] = DICTIONARY_STATES,
    inputs: Sequence[str] = DEFAULT_INPUTS,
    ts: float = 0.025,
) -> list[Trajectory]:
    """Named-column CSV runs (``models.dataset.load_dataset``) -> trajectories."""
    from models.dataset import load_dataset  # the CSV reader belongs to the data package

    columns = ("time", *states, *inputs)
    runs = load_dataset(directory, ts=ts, columns=columns)
    return [Trajectory(run.name, run.array(list(states)), run.array(list(inputs)), tuple(states), tuple(inputs))
            for run in runs]


# ---------------------------------------------------------------------- CLI
def _names(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("expected a comma-separated list of column names")
    return names


def build_parser() -> argparse.ArgumentParser:
    defaults = TrainingSettings()
    p = argparse.ArgumentParser(prog="python -m models.koopman_train", description=__doc__.split("\n")[0])
    p.add_argument("--data", default="data/nominal", help="directory of named-column CSV runs")
    p.add_argument("--out", default=None,
                   help="artefact path without extension (required; with --logs a folder); an existing "
                        "output is refused without --replace")
    p.add_argument("--replace", action="store_true",
                   help="overwrite an existing --out artefact (or the outputs in the --out folder)")
    p.add_argument("--states", type=_names, default=DEFAULT_STATES, help="state columns, comma-separated")
    p.add_argument("--inputs", type=_names, default=DEFAULT_INPUTS, help="input columns, comma-separated")
    p.add_argument("--ts", type=float, default=0.025, help="sample time in s (data are resampled to it)")
    p.add_argument("--features", type=int, default=defaults.n_features, help="d, number of learned features")
    p.add_argument("--seq-len", type=int, default=defaults.seq_len, help="p, sequence length of eq. 9")
    p.add_argument("--epochs", type=int, default=defaults.max_epochs)
    p.add_argument("--steps-per-epoch", type=int, default=defaults.steps_per_epoch)
    p.add_argument("--batch-size", type=int, default=defaults.batch_size)
    p.add_argument("--hidden", type=lambda s: tuple(int(v) for v in s.split(",")), default=defaults.hidden,
                   help="hidden layer widths, comma-separated")
    p.add_argument("--lifted-weight", type=float, default=defaults.lifted_weight)
    p.add_argument("--form", choices=MODEL_FORMS, default=defaults.form,
                   help="model form: the paper's linear eq. 5 or bilinear (input matrix depends on z)")
    p.add_argument("--dictionary", type=lambda t: tuple(n for n in t.split(",") if n),
                   default=defaults.dictionary,
                   help=f"fixed lifting functions, comma-separated, '' for none (known: {','.join(DICTIONARY)})")
    p.add_argument("--speed-knots", type=lambda t: tuple(float(v) for v in t.split(",")),
                   default=defaults.speed_knots, help="speed knots in m/s of the scheduled form, comma-separated")
    p.add_argument("--small-signal-accel", type=float, default=defaults.small_signal_accel, metavar="A0",
                   help="weigh windows by 1 / (1 + (peak |vx r| / A0)^2), A0 in m/s^2; 0 (default) for off")
    p.add_argument("--unscheduled-states", type=lambda t: tuple(n for n in t.split(",") if n),
                   default=defaults.unscheduled_states, metavar="NAMES",
                   help="states whose dynamics row is one for all speed knots (scheduled form), comma-separated")
    p.add_argument("--mirror-symmetric", action="store_true",
                   help="build the left / right mirror symmetry into the model (scheduled form)")
    p.add_argument("--even-features", type=int, default=defaults.even_features,
                   help="with --mirror-symmetric: how many of the d features are even (the rest odd)")
    p.add_argument("--servo-lag", action="store_true",
                   help="with --mirror-symmetric: the wheel-angle row is a lag of unit DC gain from the steer command")
    p.add_argument("--lateral-per-step", action="store_true",
                   help="with --mirror-symmetric: schedule the lateral rows on each step's speed in training")
    p.add_argument("--steer-bilinear", action="store_true",
                   help="with --mirror-symmetric: add a steer-bilinear term, so the steer response depends "
                        "on the state at a given speed")
    p.add_argument("--gain-anchor", type=float, default=defaults.gain_anchor, metavar="W",
                   help="weight of the gain anchor: the small-signal steer response held to local fits of the "
                        "training runs' gentle samples (scheduled form); 0 (default) for off")
    p.add_argument("--patience", type=int, default=defaults.patience, help="epochs without improvement before stopping")
    p.add_argument("--learning-rate", type=float, default=defaults.learning_rate)
    p.add_argument("--lr-decay", type=float, default=defaults.lr_decay, help="learning-rate factor per epoch")
    p.add_argument("--seed", type=int, default=defaults.seed)
    p.add_argument("--threads", type=int, default=defaults.threads, help="torch CPU threads (part of the result)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=defaults.device)
    p.add_argument("--compare-with", type=Path, default=None,
                   help="artefact JSON whose test errors this run must reproduce within 10%% (exit 3 if not)")
    p.add_argument("--logs", type=Path, nargs="+", default=None, metavar="LOG",
                   help="train from CAN logs of the contract's bus (or named-column CSVs with "
                        "--mapping); --out is then a folder (docs/identification.md)")
    p.add_argument("--log-inputs", choices=("command", "measured"), default="command",
                   help="--logs: inputs from STEER_TORQUE_CMD (CMD_VALID = 1) or the measured "
                        "STEER_ANGLE / DRIVE_TORQUE")
    p.add_argument("--mapping", type=Path, default=None, help="--logs: TOML mapping of named-column CSVs")
    p.add_argument("--vehicle", type=Path, default=None,
                   help="--logs: vehicle file of the bicycle's mass and geometry (default models/vehicle.toml)")
    p.add_argument("--dbc", type=Path, default=None, help="--logs: DBC to decode with (default the contract's)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    defaults = TrainingSettings()
    try:
        settings = TrainingSettings(
            n_features=args.features, hidden=args.hidden, seq_len=args.seq_len, batch_size=args.batch_size,
            max_epochs=args.epochs, steps_per_epoch=args.steps_per_epoch, lifted_weight=args.lifted_weight,
            form=args.form, dictionary=args.dictionary, patience=args.patience,
            speed_knots=args.speed_knots, small_signal_accel=args.small_signal_accel,
            unscheduled_states=args.unscheduled_states,
            mirror_symmetric=args.mirror_symmetric, even_features=args.even_features,
            servo_lag=args.servo_lag, lateral_per_step=args.lateral_per_step,
            steer_bilinear=args.steer_bilinear, gain_anchor=args.gain_anchor, learning_rate=args.learning_rate, lr_decay=args.lr_decay,
            seed=args.seed, threads=args.threads, device=args.device,
        )
        check_outputs(args)
        if args.logs:  # issue 20: the data come from CAN logs; --out is a folder
            from models.log_identification import load_log_runs, write_log_products
            out_folder = _log_out_folder(args.out)
            runs, meta, warnings, ts = load_log_runs(args.logs, args.ts, args.log_inputs, args.mapping, args.dbc)
            result = train(runs, ts, settings, progress=not args.no_progress, metadata=meta)
            npz_path, json_path = write_artifact(result, out_folder / "koopman")
            for path in write_log_products(out_folder, result.model, runs, result.test_runs, ts,
                                           args.vehicle, meta, warnings):
                print(f"wrote {path}")
        else:
            data_dir = Path(args.data)
            if not data_dir.is_dir():
                raise KoopmanError(f"data directory not found: {data_dir}")
            if tuple(args.states)[:3] != DICTIONARY_STATES and args.dictionary == defaults.dictionary:
                # The dictionary's formulas are for [vx, vy, yaw_rate]; other data go without it.
                print(f"note: states {args.states} are not {DICTIONARY_STATES}: training without the dictionary")
                settings = dataclasses.replace(settings, dictionary=())
            runs = load_trajectories(data_dir, args.states, args.inputs, args.ts)
            meta = {"data_dir": str(data_dir), "data_hash": dataset_hash(data_dir), "n_runs": len(runs)}
            result = train(runs, args.ts, settings, progress=not args.no_progress, metadata=meta,
                           friction=friction_of_runs(data_dir))
            npz_path, json_path = write_artifact(result, args.out)
    except Exception as e:  # noqa: BLE001 - CLI boundary: one line unless --debug
        if args.debug or not _is_input_error(e):
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    meta = result.model.metadata
    print(f"wrote {npz_path} and {json_path} in {result.seconds:.0f} s "
          f"(best epoch {result.best_epoch}, spectral radius of A {meta['spectral_radius_A']:.4f})")
    for name, figures in meta["test_errors"].items():
        print(f"  test {name:>10}: one-step max/avg/rmse {figures['one_step_max']:.4f} / "
              f"{figures['one_step_avg']:.4f} / {figures['one_step_rmse']:.4f}, "
              f"{OPEN_LOOP_STEPS}-step rmse {figures['open_loop_rmse']:.4f}")
    if args.compare_with is not None:
        reference = json.loads(Path(args.compare_with).read_text())
        if reference.get("settings") != meta.get("settings"):
            # Another form or other settings: its figures are not a reference for this one.
            changed = sorted(k for k in set(reference.get("settings", {})) | set(meta["settings"])
                             if reference.get("settings", {}).get(k) != meta["settings"].get(k))
            print(f"not compared with {args.compare_with}: its training settings differ ({', '.join(changed)})")
            return 0
        return 0 if compare_test_errors(meta["test_errors"], args.compare_with) else 3
    return 0


#: Files ``--logs --out DIR`` writes into its folder.
LOG_OUTPUTS = ("koopman.npz", "koopman.json", "bicycle.json", "report.json", "report.md")


def check_outputs(args: argparse.Namespace) -> None:
    """Each ``--logs`` file a regular file of at most ``LOG_FILE_MAX_BYTES``; and ``--out``
    before any training (issue 38, item 11): given (no default points at a
    committed artefact), never one of the inputs, and an existing artefact (or, with
    ``--logs``, a folder holding its outputs) only with ``--replace``.

    Raises:
        KoopmanError: naming the option (or the log), the path and the problem.
    """
    from models.errors import OutputPathError
    from models.input_files import LOG_FILE_MAX_BYTES, check_file_size
    from models.output_paths import check_output_file, check_output_folder

    if args.out is None:
        raise KoopmanError("--out is required: the artefact path without extension (with --logs, a folder "
                           "for koopman.npz/.json, bicycle.json, report.md)")
    for log in args.logs or ():   # each log bounded before any reader takes it whole
        if Path(log).exists():    # (a missing one is the log reader's error)
            check_file_size(log, LOG_FILE_MAX_BYTES, KoopmanError)
    out = Path(args.out)
    inputs = [*(args.logs or [Path(args.data)]),
              *(path for path in (args.mapping, args.vehicle, args.dbc, args.compare_with) if path is not None)]
    try:
        if args.logs:
            check_output_folder(out, "--out", LOG_OUTPUTS, replace=args.replace, inputs=inputs)
        else:
            for suffix in (".npz", ".json"):
                check_output_file(out.with_suffix(suffix), "--out", replace=args.replace, inputs=inputs)
    except OutputPathError as error:
        raise KoopmanError(str(error)) from None


def _log_out_folder(out: str | Path) -> Path:
    """``--out`` of ``--logs``: a folder (created; its parent must exist)."""
    folder = Path(out)
    if not folder.parent.is_dir():
        raise KoopmanError(f"--out {folder}: folder {folder.parent} does not exist")
    folder.mkdir(exist_ok=True)
    return folder


def compare_test_errors(test_errors: dict, reference_json: Path, tolerance: float = 0.10) -> bool:
    """Print the relative change of every test figure against a reference artefact JSON.

    Returns True when all are within ``tolerance`` (relative).
    """
    reference = json.loads(Path(reference_json).read_text())["test_errors"]
    worst = 0.0
    for name, figures in test_errors.items():
        for key, value in figures.items():
            ref = reference[name][key]
            change = abs(value - ref) / max(abs(ref), 1e-12)
            worst = max(worst, change)
            print(f"  {name:>10} {key:<21} {value:.5f} vs {ref:.5f} ({100 * change:+.1f} %)")
    ok = worst <= tolerance
    print(f"largest relative change vs {reference_json}: {100 * worst:.1f} % "
          f"({'within' if ok else 'OUTSIDE'} {100 * tolerance:.0f} %)")
    return ok


def _is_input_error(e: Exception) -> bool:
    from models.errors import ModelError

    return isinstance(e, (ModelError, OSError, ValueError))


if __name__ == "__main__":
    sys.exit(main())

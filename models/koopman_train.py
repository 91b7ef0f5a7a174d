"""Training of the deep Koopman model in torch (build time only; the ECU never imports this).

The network, its two forms (the paper's linear eq. 5 and the bilinear form that can give a
speed-dependent steering response) and the loss are in ``models/koopman_train_net.py``.
Everything is in min-max normalised units (bounds from the training runs only);
``models/koopman.py`` folds the normalisation into physical-unit matrices. The other parts
of a training, one job each: the hyper-parameters ``models/koopman_settings.py``
(``TrainingSettings``), the data (read, split by run, bounds) ``models/koopman_data.py``,
the windows in torch ``models/koopman_train_windows.py`` (``SequenceSet``); their names stay
importable from here. The command line is ``models/koopman_cli.py`` (``main``,
``build_parser``), which imports this module when it trains; this module imports it only
to run as ``python -m models.koopman_train``, so neither imports the other on import.

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

CLI (``models/koopman_cli.py``): ``python -m models.koopman_train --data data/nominal --out
models/artifacts/dk_d5``; ``--states/--inputs/--ts`` train on any named-column CSV data set;
``--logs LOG [LOG ...] --out DIR`` trains from CAN logs of the contract's bus and writes the
artefact, a fitted bicycle and a report into DIR (``models/log_identification.py``,
docs/identification.md).
"""
from __future__ import annotations

import copy
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from models.koopman import (KoopmanError, KoopmanModel, MinMaxScaling, NormalisedKoopman, check_dictionary,
                            dictionary_features, knot_weights, save_artifact)
from models.koopman_data import dictionary_scaling_of, fit_scaling, split_runs
from models.koopman_data import dataset_hash, load_trajectories  # noqa: F401 - re-exported
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors
from models.koopman_settings import TrainingSettings, settings_json
from models.koopman_settings import DEFAULT_INPUTS, DEFAULT_STATES  # noqa: F401 - re-exported
from models.koopman_train_anchor import GainAnchor, anchor_targets, lateral_velocity_targets
from models.koopman_train_net import KoopmanNet, least_squares_start
from models.koopman_train_symmetric import SERVO_INPUT, SERVO_STATE, MirrorKoopmanNet, parities, shared_servo_scaling
from models.koopman_train_windows import SequenceSet


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


def _known_coordinates(run: Trajectory, state_scaling: MinMaxScaling, dictionary: tuple[str, ...],
                       dictionary_scaling: MinMaxScaling | None) -> np.ndarray:
    """[x_n, psi_n] of one run, (n, n_x + n_dict)."""
    parts = [state_scaling.normalise(run.states)]
    if dictionary:
        parts.append(dictionary_scaling.normalise(dictionary_features(dictionary, run.states)))
    return np.hstack(parts)


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
    vy_targets = lateral_velocity_targets(anchor_targets_) if settings.gain_anchor_vy > 0 else None
    anchor = (None if anchor_targets_ is None
              else GainAnchor(anchor_targets_, state_scaling, input_scaling, knots, device, state_names, input_names,
                              vy_targets, dictionary, dictionary_scaling))
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
        if vy_targets is not None:
            running["anchor_vy"] = 0.0
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
                losses.update(anchor.losses(net))
                losses["prediction"] = losses["prediction"] + settings.gain_anchor * losses["anchor"]
                if vy_targets is not None:
                    losses["prediction"] = losses["prediction"] + settings.gain_anchor_vy * losses["anchor_vy"]
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
    if vy_targets is not None:
        meta["gain_anchor_vy_targets"] = vy_targets.as_json()
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


def _steer_input(input_names: Sequence[str]) -> int:
    """Index of the steer command (the steer-bilinear term's input); KoopmanError without one."""
    if SERVO_INPUT not in input_names:
        raise KoopmanError(f"steer_bilinear needs {SERVO_INPUT!r} among the inputs {tuple(input_names)}")
    return list(input_names).index(SERVO_INPUT)


def write_artifact(result: TrainingResult, out: str | Path) -> tuple[Path, Path]:
    """Save a training result as ``<out>.npz`` + ``<out>.json``."""
    return save_artifact(out, result.learned, result.model.metadata)


if __name__ == "__main__":
    from models.koopman_cli import main

    sys.exit(main())

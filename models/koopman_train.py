"""Training of the deep Koopman model in torch (build time only; the ECU never imports this).

Network (Fig. 2, Remark 4): encoder Phi = MLP with 3 hidden layers of 128 tanh units giving d
learned features; lifted state z = [x; Phi(x)] (eq. 6), x = C_P z (eq. 7); A and B are
bias-free linear maps (eq. 5); a decoder Phi^-1 (mirror of the encoder) for the
reconstruction loss. Everything is in min-max normalised units (bounds from the training
runs only); ``models/koopman.py`` folds the normalisation into physical-unit matrices.

Loss per sequence x_k..x_{k+p-1}, u_k..u_{k+p-2} (all terms are means, i.e. eqs. 9 and 11
divided by their number of terms):

- L1, multi-step prediction (eqs. 9-10), rolled out in the LIFTED space from z_k:
  z_hat_{k+i} = A z_hat_{k+i-1} + B u_{k+i-1}, x_hat_{k+i} = C_P z_hat_{k+i}, i = 1..p-1.
  (Eq. 10 as printed re-lifts the true z_{k+i-1}; rolling out is what the MPC does.)
- L2, reconstruction (eq. 11): x vs Phi^-1(Phi(x)) over the sequence.
- L3, lifted consistency (OUR ADDITION, weight ``lifted_weight``): Phi(x_{k+i}) of the true
  future state vs the rolled-out features of z_hat_{k+i}. It keeps the learned features
  predictable by A, B, which the MPC relies on over its horizon.

Optimiser: Adam with an exponential learning-rate decay per epoch (the paper says steepest
descent; Adam is our choice). Runs are split into train / validation / test BY RUN, never by
sample; early stopping on the validation loss keeps the best weights. Deterministic for a
seed: ``torch.manual_seed``, ``use_deterministic_algorithms``, a fixed torch thread count
(``threads``, default 1: on the shared 2-core machine two torch threads ran 5x slower than
one, 2 it/s vs 9 it/s at load ~6), a seeded batch sampler, and a fixed number of steps per
epoch (never a wall-clock budget).

CLI: ``python -m models.koopman_train --data data/nominal --out models/artifacts/dk_d5``;
``--states/--inputs/--ts`` train on any named-column CSV data set.
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from models.koopman import KoopmanError, KoopmanModel, MinMaxScaling, NormalisedKoopman, save_artifact
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors

DEFAULT_STATES = ("vx", "vy", "yaw_rate")
DEFAULT_INPUTS = ("torque", "steer")


@dataclass(frozen=True)
class TrainingSettings:
    """Hyper-parameters of one training run (all stored in the artefact's JSON).

    ``seq_len`` is p of eq. 9: p states per sequence, p - 1 predicted steps.
    One epoch = ``steps_per_epoch`` Adam steps on batches drawn with replacement.
    """

    n_features: int = 5
    hidden: tuple[int, ...] = (128, 128, 128)
    seq_len: int = 31
    batch_size: int = 128
    learning_rate: float = 1e-3
    lr_decay: float = 0.93
    max_epochs: int = 25
    steps_per_epoch: int = 200
    patience: int = 6
    recon_weight: float = 1.0
    lifted_weight: float = 1.0
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
            "threads": self.threads >= 1,
            "recon_weight": self.recon_weight >= 0,
            "lifted_weight": self.lifted_weight >= 0,
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
    net: "KoopmanNet"
    train_runs: list[str]
    val_runs: list[str]
    test_runs: list[str]
    best_epoch: int
    best_val_loss: float
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0


class KoopmanNet(nn.Module):
    """Encoder, decoder and the bias-free A, B of eq. 5, all in normalised units."""

    def __init__(self, n_x: int, n_u: int, n_features: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.n_x, self.n_u, self.n_features = n_x, n_u, n_features
        self.n_z = n_x + n_features
        self.encoder = _mlp(n_x, hidden, n_features)
        self.decoder = _mlp(n_features, tuple(reversed(hidden)), n_x)
        self.A = nn.Linear(self.n_z, self.n_z, bias=False)
        self.B = nn.Linear(n_u, self.n_z, bias=False)
        with torch.no_grad():
            # Start near "nothing moves in 25 ms": a stable, well-conditioned first guess.
            self.A.weight.copy_(torch.eye(self.n_z) + 0.01 * self.A.weight)
            self.B.weight.mul_(0.1)

    @torch.no_grad()
    def warm_start(self, a_xx: np.ndarray, b_x: np.ndarray) -> None:
        """Start the state rows of A, B from a linear least-squares fit (normalised units).

        a_xx (n_x, n_x), b_x (n_x, n_u). The features start with no influence on x, so the
        first rollouts are those of the best linear model; training only has to add what the
        features explain.
        """
        self.A.weight[: self.n_x, : self.n_x] = torch.as_tensor(a_xx, dtype=self.A.weight.dtype)
        self.A.weight[: self.n_x, self.n_x :] = 0.0
        self.B.weight[: self.n_x] = torch.as_tensor(b_x, dtype=self.B.weight.dtype)

    def lift(self, x_n: torch.Tensor) -> torch.Tensor:
        """x_n (..., n_x) -> z_n (..., n_z) = [x_n; Phi(x_n)] (eq. 6)."""
        return torch.cat([x_n, self.encoder(x_n)], dim=-1)

    def rollout(self, z0: torch.Tensor, inputs_n: torch.Tensor) -> torch.Tensor:
        """z0 (batch, n_z), inputs_n (batch, n_steps, n_u) -> z_hat (batch, n_steps, n_z)."""
        forced = self.B(inputs_n)
        z = z0
        out = []
        for i in range(inputs_n.shape[1]):
            z = self.A(z) + forced[:, i]
            out.append(z)
        return torch.stack(out, dim=1)

    def losses(self, x_n: torch.Tensor, u_n: torch.Tensor) -> dict[str, torch.Tensor]:
        """x_n (batch, p, n_x), u_n (batch, p - 1, n_u) -> the three loss terms (scalars)."""
        features = self.encoder(x_n)
        z0 = torch.cat([x_n[:, 0], features[:, 0]], dim=-1)
        z_hat = self.rollout(z0, u_n)
        prediction = torch.mean((z_hat[..., : self.n_x] - x_n[:, 1:]) ** 2)  # eqs. 9-10
        # eq. 11 as printed reconstructs x_k, the first state of the sequence; the batch's
        # overlapping windows cover the same states, at a third of the decoder cost.
        reconstruction = torch.mean((self.decoder(features[:, 0]) - x_n[:, 0]) ** 2)
        lifted = torch.mean((z_hat[..., self.n_x :] - features[:, 1:]) ** 2)  # our addition
        return {"prediction": prediction, "reconstruction": reconstruction, "lifted": lifted}

    def export(self, state_scaling: MinMaxScaling, input_scaling: MinMaxScaling) -> NormalisedKoopman:
        """The learned weights as float64 numpy arrays (encoder, A_n, B_n)."""
        layers = [m for m in self.encoder if isinstance(m, nn.Linear)]
        encoder = tuple(
            (l.weight.detach().cpu().double().numpy().copy(), l.bias.detach().cpu().double().numpy().copy())
            for l in layers
        )
        return NormalisedKoopman(
            encoder=encoder,
            A_n=self.A.weight.detach().cpu().double().numpy().copy(),
            B_n=self.B.weight.detach().cpu().double().numpy().copy(),
            state_scaling=state_scaling,
            input_scaling=input_scaling,
        )


def _mlp(n_in: int, hidden: Sequence[int], n_out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    width = n_in
    for h in hidden:
        layers += [nn.Linear(width, h), nn.Tanh()]
        width = h
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


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


def _linear_fit(
    runs: Sequence[Trajectory], state_scaling: MinMaxScaling, input_scaling: MinMaxScaling
) -> tuple[np.ndarray, np.ndarray]:
    """Bias-free least squares x_n+ = A x_n + B u_n over the runs -> (A (n_x, n_x), B (n_x, n_u))."""
    regressors = np.concatenate(
        [np.hstack([state_scaling.normalise(r.states[:-1]), input_scaling.normalise(r.inputs[:-1])]) for r in runs]
    )
    targets = np.concatenate([state_scaling.normalise(r.states[1:]) for r in runs])
    coef, *_ = np.linalg.lstsq(regressors, targets, rcond=None)
    n_x = targets.shape[1]
    return coef[:n_x].T, coef[n_x:].T


class SequenceSet:
    """All length-p windows of a set of runs, gathered on the fly from one flat tensor."""

    def __init__(
        self,
        runs: Sequence[Trajectory],
        seq_len: int,
        state_scaling: MinMaxScaling,
        input_scaling: MinMaxScaling,
        device: torch.device,
        role: str,
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
        self.states = torch.as_tensor(states, dtype=torch.float32, device=device)
        self.inputs = torch.as_tensor(inputs, dtype=torch.float32, device=device)
        self.starts = torch.as_tensor(np.concatenate(starts), dtype=torch.long, device=device)
        self.offsets = torch.arange(seq_len, device=device)

    def __len__(self) -> int:
        return int(self.starts.numel())

    def batch(self, which: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Window indices (b,) -> x_n (b, p, n_x), u_n (b, p - 1, n_u)."""
        rows = self.starts[which][:, None] + self.offsets
        return self.states[rows], self.inputs[rows[:, :-1]]


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
) -> TrainingResult:
    """Fit the deep Koopman model on ``runs`` (split by run) and return it in physical units.

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
    train_runs, val_runs, test_runs = split_runs(runs, settings)
    state_scaling, input_scaling = fit_scaling(train_runs)
    train_set = SequenceSet(train_runs, settings.seq_len, state_scaling, input_scaling, device, "training")
    val_set = SequenceSet(val_runs, settings.seq_len, state_scaling, input_scaling, device, "validation")
    # A fixed, evenly spread subset of validation windows keeps the check cheap and exact.
    val_index = torch.as_tensor(
        np.unique(np.linspace(0, len(val_set) - 1, min(settings.val_windows, len(val_set))).astype(int)),
        device=device,
    )

    net = KoopmanNet(len(state_names), len(input_names), settings.n_features, settings.hidden)
    if settings.warm_start:
        net.warm_start(*_linear_fit(train_runs, state_scaling, input_scaling))
    net = net.to(device)
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
        for step in range(settings.steps_per_epoch):
            which = torch.randint(len(train_set), (settings.batch_size,), generator=sampler).to(device)
            x_n, u_n = train_set.batch(which)
            losses = net.losses(x_n, u_n)
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
        val_loss = _validation_loss(net, val_set, val_index, settings)
        history.append({"epoch": epoch, **running, "val": val_loss})
        if val_loss < best_val:
            best_val, best_epoch, stale = val_loss, epoch, 0
            best_state = copy.deepcopy(net.state_dict())
        else:
            stale += 1
            if stale >= settings.patience:
                bar.write(f"early stop after epoch {epoch}: best validation loss {best_val:.3e} at epoch {best_epoch}")
                break
    bar.close()
    net.load_state_dict(best_state)
    net.eval()

    learned = net.export(state_scaling, input_scaling)
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
        torch_version=torch.__version__,
        device=str(device),
    )
    model = KoopmanModel.from_normalised(learned, ts, state_names, input_names, meta)
    meta["spectral_radius_A"] = model.spectral_radius()
    meta["test_errors"] = prediction_errors(model, test_runs, open_loop_steps=OPEN_LOOP_STEPS)
    meta["test_open_loop_steps"] = OPEN_LOOP_STEPS
    elapsed = time.perf_counter() - started
    meta["training_seconds"] = round(elapsed, 1)
    model.metadata = meta
    return TrainingResult(
        model=model, learned=learned, net=net,
        train_runs=[r.name for r in train_runs], val_runs=[r.name for r in val_runs],
        test_runs=[r.name for r in test_runs], best_epoch=best_epoch, best_val_loss=best_val,
        history=history, seconds=elapsed,
    )


@torch.no_grad()
def _validation_loss(net: KoopmanNet, val_set: SequenceSet, index: torch.Tensor, settings: TrainingSettings) -> float:
    net.eval()
    total, count = 0.0, 0
    for chunk in torch.split(index, 1024):
        x_n, u_n = val_set.batch(chunk)
        total += float(_total(net.losses(x_n, u_n), settings)) * len(chunk)
        count += len(chunk)
    return total / count


def settings_json(settings: TrainingSettings) -> dict:
    out = asdict(settings)
    out["hidden"] = list(settings.hidden)
    return out


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
    states: Sequence[str] = DEFAULT_STATES,
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
    p.add_argument("--out", default="models/artifacts/dk_d5", help="artefact path without extension")
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
    p.add_argument("--seed", type=int, default=defaults.seed)
    p.add_argument("--threads", type=int, default=defaults.threads, help="torch CPU threads (part of the result)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=defaults.device)
    p.add_argument("--compare-with", type=Path, default=None,
                   help="artefact JSON whose test errors this run must reproduce within 10%% (exit 3 if not)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        settings = TrainingSettings(
            n_features=args.features, hidden=args.hidden, seq_len=args.seq_len, batch_size=args.batch_size,
            max_epochs=args.epochs, steps_per_epoch=args.steps_per_epoch, lifted_weight=args.lifted_weight,
            seed=args.seed, threads=args.threads, device=args.device,
        )
        data_dir = Path(args.data)
        if not data_dir.is_dir():
            raise KoopmanError(f"data directory not found: {data_dir}")
        runs = load_trajectories(data_dir, args.states, args.inputs, args.ts)
        meta = {"data_dir": str(data_dir), "data_hash": dataset_hash(data_dir), "n_runs": len(runs)}
        result = train(runs, args.ts, settings, progress=not args.no_progress, metadata=meta)
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
        return 0 if compare_test_errors(meta["test_errors"], args.compare_with) else 3
    return 0


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

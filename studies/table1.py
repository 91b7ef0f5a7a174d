"""Table I: prediction errors of the learned model forms and of the physics models, over seeds.

Rows (``ROWS``): the first default model (speed-scheduled lift with the measured wheel angle
in the state), the scheduled form on [vx, vy, r] alone (what the wheel angle adds), the
bilinear form with the dictionary, the paper's linear form (eq. 5), and the mirror-symmetric
form with its steer-bilinear term, without and with the gain anchor (the latter the default,
``DEFAULT_ROW``, since issue 14's step steer); each trained with ``SEEDS``
(5 seeds: the seed draws the weights AND the train / validation / test split by run) on the
same data set (default ``data/wide``, the default artefact's). Beside them, fitted or built
on each seed's split (``closed_form_rows``): DMDc, EDMDc (monomials), the trainer's
least-squares lifts ``--form edmdc-linear`` / ``edmdc-bilinear`` (the physics dictionary,
fitted by ``models.lifted_least_squares`` as the trainer fits them, on the trainer's default
states), LMPC's linear bicycle (speed held) and NMPC's single track (nominal parameters). Every model is evaluated on its seed's held-out test runs:
one-step RMSE, and open-loop RMSE over 1 s (40 steps) and 2 s (80 steps) with the recorded
inputs, of vx, vy and yaw rate; each cell is the mean +- the standard deviation over the seeds.

Writes ``results/table1.md``, ``results/table1.json``, ``results/fig6_prediction_errors.png``
(seed 0's one-step errors along a test run, as the paper's Fig. 6) and
``results/prediction_horizon_rmse.png`` (RMSE against the prediction step, mean over seeds).
Trained models are cached in ``build/table1/`` (keyed by data hash, settings and states);
the default row's seed 0 reuses the committed artefact when it matches. The missing models
are trained first, each training a task of the campaigns' executors (a local Ray with one
worker per core by default, ``--address`` for a cluster, ``--serial`` in this process);
training all rows takes about an hour on 2 cores; the table can be built in several
sittings (the cache keeps what is done; ``--rows`` / ``--seeds`` select).
CLI: ``python -m studies.table1 [--data data/wide] [--rows 0,4] [--seeds 0,1,2,3,4]
[--address ADDR] [--workers N] [--serial]``. The closed-form rows alone, in minutes:
``studies/table1_least_squares.py`` (``make table1-lsq``).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from hil.errors import HilError
from models.errors import ModelError
from models.koopman import DEFAULT_ARTIFACT, KoopmanError, KoopmanModel
from models.koopman_baselines import DMDc, EDMDc
from models.koopman_data import dataset_hash, load_trajectories, split_runs
from models.koopman_metrics import Predictor, Trajectory, open_loop_windows
from models.koopman_settings import TrainingSettings
from models.lifted_least_squares import fit_least_squares
from models.local_lateral_fit import friction_of_runs
from studies.model_fidelity import BicyclePredictor, SingleTrackPredictor

TS = 0.025
SEEDS = (0, 1, 2, 3, 4)
VEHICLE_STATES = ("vx", "vy", "yaw_rate")
WHEEL_STATES = (*VEHICLE_STATES, "steer_measured")
HORIZONS = {"1 s": 40, "2 s": 80}
STATE_LABELS = {"vx": ("E_x", "m/s"), "vy": ("E_y", "m/s"), "yaw_rate": ("E_r", "rad/s")}
#: The trainer's closed-form lifts as rows: label -> ``--form`` (models/lifted_least_squares.py).
LEAST_SQUARES_ROWS = {
    "EDMDc physics dictionary, linear (edmdc-linear)": "edmdc-linear",
    "EDMDc physics dictionary, bilinear (edmdc-bilinear)": "edmdc-bilinear",
}
#: The rows fitted by least squares (the others without training are physics models).
FITTED_ROWS = ("DMDc", "EDMDc", *LEAST_SQUARES_ROWS)


@dataclass(frozen=True)
class Row:
    """A learned row: its label, TrainingSettings overrides and the model's states."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)
    states: tuple[str, ...] = WHEEL_STATES


ROWS = (
    # The first default (sessions before issue 14's item 4): TrainingSettings' own defaults.
    Row("DK scheduled + wheel angle, d=5"),
    Row("DK scheduled, d=5", {}, VEHICLE_STATES),
    Row("DK bilinear + dictionary, d=5", {"form": "bilinear"}, VEHICLE_STATES),
    Row("DK paper form (linear), d=5", {"form": "linear", "dictionary": ()}, VEHICLE_STATES),
    # The mirror-symmetric form with its steer-bilinear term (models/koopman_train_symmetric.py).
    Row("mirror-symmetric, d=8 (2 even), servo lag, steer-bilinear N(v)",
        {"mirror_symmetric": True, "n_features": 8, "even_features": 2, "servo_lag": True,
         "steer_bilinear": True}),
    # The same with the gain anchor (models/koopman_train_anchor.py), weight 10: the default
    # artefact's form (make train's KOOPMAN_FORM, mk/koopman.mk).
    Row("mirror-symmetric steer-bilinear + gain anchor (w = 10) (default)",
        {"mirror_symmetric": True, "n_features": 8, "even_features": 2, "servo_lag": True,
         "steer_bilinear": True, "gain_anchor": 10.0}),
)
#: The row of the committed default artefact (models/artifacts/dk_d5): its seed 0.
DEFAULT_ROW = ROWS[-1]


class VehicleStates:
    """Adapts a predictor to the data's states: it sees its own leading states, returns vx, vy, r."""

    def __init__(self, predictor: Predictor, n_states: int) -> None:
        self.predictor, self.n_states = predictor, n_states

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, >= n_states), inputs (batch, n, 2) -> (batch, n, 3)."""
        return self.predictor.predict(x0[:, : self.n_states], inputs)[..., :3]


def _slug(label: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", label.lower()).strip("_")


def cached_model_path(row: Row, seed: int, models_dir: Path) -> Path:
    """Where Table I caches ``row``'s model of ``seed`` (``.npz``, its ``.json`` beside it)."""
    return models_dir / f"{_slug(row.label)}_s{seed}.npz"


def cached_model(row: Row, seed: int, data_hash: str, models_dir: Path) -> KoopmanModel | None:
    """The row's model for ``seed`` when a matching cached (or the committed) artefact
    exists: same data hash, training settings and states; else None."""
    from models import koopman_train  # torch is needed here only

    wanted = koopman_train.settings_json(koopman_train.TrainingSettings(**{**row.overrides, "seed": seed}))
    for candidate in (DEFAULT_ARTIFACT, cached_model_path(row, seed, models_dir)):
        json_path = candidate.with_suffix(".json")
        if candidate.is_file() and json_path.is_file():
            meta = json.loads(json_path.read_text())
            if (meta.get("data_hash") == data_hash and meta.get("settings") == wanted
                    and tuple(meta.get("state_names", ())) == row.states):
                return KoopmanModel.load(candidate)
    return None


@dataclass(frozen=True)
class TrainingTask:
    """One training of Table I for a worker (picklable): ``row`` with ``seed`` on the data
    set in ``data_dir`` (whose hash is ``data_hash``), written into ``models_dir``."""

    key: str
    row: Row
    seed: int
    data_dir: Path
    data_hash: str
    models_dir: Path


def train_task(task: TrainingTask) -> dict[str, Any]:
    """Train and cache one model (a Ray task or in this process); never raises.

    Returns {path, seconds} or {error}. The worker reads the data set itself, so on a
    cluster every node needs it at the same path (docs/campaign.md).
    """
    from models import koopman_train  # torch is needed here only

    try:
        runs = koopman_train.load_trajectories(task.data_dir, states=WHEEL_STATES)
        if koopman_train.dataset_hash(task.data_dir) != task.data_hash:
            return {"error": f"{task.data_dir} differs from the data set the table was started on"}
        row = task.row
        own = [Trajectory(r.name, r.states[:, : len(row.states)], r.inputs, row.states, r.input_names)
               for r in runs]
        settings = koopman_train.TrainingSettings(**{**row.overrides, "seed": task.seed})
        result = koopman_train.train(own, TS, settings, metadata={
            "data_dir": str(task.data_dir), "data_hash": task.data_hash, "n_runs": len(runs)}, progress=False,
            friction=friction_of_runs(task.data_dir))
        path = cached_model_path(row, task.seed, task.models_dir)
        koopman_train.write_artifact(result, path.with_suffix(""))
    except Exception as e:  # noqa: BLE001 - reported as this training's failure
        return {"error": f"{type(e).__name__}: {e}"}
    return {"path": str(path), "seconds": result.seconds}


def train_missing(rows: Sequence[Row], seeds: Sequence[int], data_dir: Path, data_hash: str,
                  models_dir: Path, executor_options: dict[str, Any] | None = None) -> None:
    """Train every (row, seed) without a cached model, as tasks of the campaigns' executors
    (``studies.campaign.executors``: a local Ray by default, a cluster by address, or this
    process with ``serial``). Raises KoopmanError naming every training that failed."""
    from tqdm import tqdm

    from studies.campaign.executors import open_executor

    tasks = [TrainingTask(f"{row.label} seed {seed}", row, seed, data_dir, data_hash, models_dir)
             for seed in seeds for row in rows if cached_model(row, seed, data_hash, models_dir) is None]
    if not tasks:
        return
    print(f"training {len(tasks)} models of Table I", file=sys.stderr, flush=True)
    executor = open_executor(train_task, **(executor_options or {}))
    failures = []
    try:
        with tqdm(total=len(tasks), desc="Table I trainings", unit="model", dynamic_ncols=True) as bar:
            for task, outcome, worker_error in executor.run(tasks):
                error = worker_error or (outcome or {}).get("error")
                if error:
                    failures.append(f"{task.key}: {error}")
                else:
                    print(f"{task.key}: trained in {outcome['seconds']:.0f} s -> {outcome['path']}",
                          file=sys.stderr, flush=True)
                bar.update(1)
    finally:
        executor.close()
    if failures:
        raise KoopmanError("trainings failed (the others are cached): " + "; ".join(failures))


def evaluate(predictor: Predictor, test_runs: Sequence[Trajectory]) -> dict[str, dict[str, float]]:
    """{state: {one_step_rmse, 1 s, 2 s}} over vx, vy, yaw rate on the test runs."""
    x0, u1, truth1 = open_loop_windows(test_runs, 1)
    one_step = np.sqrt(np.mean((predictor.predict(x0, u1)[:, 0] - truth1[:, 0, :3]) ** 2, axis=0))
    figures = {s: {"one_step_rmse": float(one_step[j])} for j, s in enumerate(VEHICLE_STATES)}
    for label, steps in HORIZONS.items():
        x0, inputs, truth = open_loop_windows(test_runs, steps, 5)
        rmse = np.sqrt(np.mean((predictor.predict(x0, inputs) - truth[..., :3]) ** 2, axis=(0, 1)))
        for j, s in enumerate(VEHICLE_STATES):
            figures[s][label] = float(rmse[j])
    return figures


def horizon_curve(predictor: Predictor, test_runs: Sequence[Trajectory], steps: int = 40) -> np.ndarray:
    """RMSE per prediction step (steps, 3)."""
    x0, inputs, truth = open_loop_windows(test_runs, steps, 5)
    return np.sqrt(np.mean((predictor.predict(x0, inputs) - truth[..., :3]) ** 2, axis=0))


def baselines(train_runs: Sequence[Trajectory]) -> dict[str, tuple[Predictor, float | None, str]]:
    """The non-learned rows for one split: (predictor on the data's states, rho, note)."""
    vehicle = [Trajectory(r.name, r.states[:, :3], r.inputs, VEHICLE_STATES, r.input_names) for r in train_runs]
    dmdc = DMDc().fit(vehicle)
    edmdc = EDMDc(degree=3).fit(vehicle)
    return {
        "DMDc": (VehicleStates(dmdc, 3), dmdc.spectral_radius(), "x+ = A x + B u + c, least squares"),
        "EDMDc": (VehicleStates(edmdc, 3), edmdc.spectral_radius(),
                  "fixed dictionary of degree 2-3 monomials, least squares (ridge 1e-6)"),
        "linear bicycle (LMPC)": (VehicleStates(BicyclePredictor(), 3), None,
                                  "nominal parameters, speed held at its start value"),
        "single track (NMPC)": (VehicleStates(SingleTrackPredictor(), 3), None,
                                "nominal parameters, Magic Formula tyres, RK4 at Ts"),
    }


def least_squares_rows(runs: Sequence[Trajectory], seed: int,
                       test_runs: Sequence[Trajectory]) -> dict[str, tuple[Predictor, float | None, str]]:
    """The trainer's ``--form edmdc-*`` lifts for one seed: fitted by
    ``models.lifted_least_squares.fit_least_squares`` on ``runs`` (the data's runs with the
    trainer's default states, WHEEL_STATES) split as the trainer splits them for ``seed``, as
    ``python -m models.koopman_train --form edmdc-linear --seed SEED`` fits them.

    Raises:
        KoopmanError: the fit's test runs differ from the table's for this seed.
    """
    rows = {}
    for label, form in LEAST_SQUARES_ROWS.items():
        model = fit_least_squares(runs, TS, form, TrainingSettings(seed=seed)).model
        if model.metadata["split"]["test"] != [r.name for r in test_runs]:
            raise KoopmanError(f"{label} seed {seed}: the fit's test runs differ from the table's split")
        rows[label] = (VehicleStates(model, len(model.state_names)), model.spectral_radius(),
                       f"{form} of the trainer, closed form, states {', '.join(model.state_names)}, "
                       f"dictionary {', '.join(model.dictionary)}, n_z = {model.n_z}")
    return rows


def closed_form_rows(runs: Sequence[Trajectory], seed: int, train_runs: Sequence[Trajectory],
                     test_runs: Sequence[Trajectory]) -> dict[str, tuple[Predictor, float | None, str]]:
    """Every row without a training, in the table's order: DMDc, EDMDc, the trainer's
    least-squares lifts, the bicycle, the single track (``baselines``, ``least_squares_rows``)."""
    physics = baselines(train_runs)
    fitted = {**physics, **least_squares_rows(runs, seed, test_runs)}
    order = [*FITTED_ROWS, *(label for label in physics if label not in FITTED_ROWS)]
    return {label: fitted[label] for label in order}


def _mean_sd(values: Sequence[float]) -> str:
    values = np.asarray(values, dtype=float)
    return f"{values.mean():.4f} ± {values.std(ddof=1):.4f}" if values.size > 1 else f"{values.mean():.4f}"


def markdown_table(rows: list[dict], data_dir: Path,
                   generated_by: str = "`make table1` (`python -m studies.table1`)",
                   title: str = "Table I: prediction errors on held-out test runs, over seeds") -> str:
    """Rows {label, seeds: [figures per seed], rho, epochs, note} -> results/table1.md."""
    head = ["model", "seeds"]
    head += [f"1-step RMSE {s}" for s in VEHICLE_STATES]
    head += [f"{h} RMSE {s}" for h in HORIZONS for s in VEHICLE_STATES]
    head += ["max rho(A)", "best / run epochs"]
    lines = [f"# {title}", "",
             f"Data `{data_dir}`. Each seed draws the weights and the split by run; every model is evaluated "
             "on its seed's test runs. 1-step RMSE of x_(k+1|k); 1 s / 2 s: open-loop rollouts of 40 / 80 "
             f"steps (Ts = {TS} s) with the recorded inputs, started every 5 samples, RMSE over all predicted "
             "steps. Cells: mean ± standard deviation over the seeds (m/s, m/s, rad/s). rho(A): the largest "
             f"spectral radius of the lifted A (over the speed knots for the scheduled form). Generated by "
             f"{generated_by}.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        per_seed = row["seeds"]
        cells = [row["label"], str(len(per_seed))]
        cells += [_mean_sd([f[s]["one_step_rmse"] for f in per_seed]) for s in VEHICLE_STATES]
        cells += [_mean_sd([f[s][h] for f in per_seed]) for h in HORIZONS for s in VEHICLE_STATES]
        cells.append("-" if row["rho"] is None else f"{max(row['rho']):.4f}")
        cells.append(", ".join(row["epochs"]) if row["epochs"] else "-")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", *[f"- {row['label']}: {row['note']}" for row in rows if row.get("note")], ""]
    return "\n".join(lines)


def plot_figures(out_dir: Path, traces: dict[str, np.ndarray], horizons: dict[str, np.ndarray],
                 run: Trajectory) -> list[Path]:
    """Fig. 6 style one-step error traces (seed 0), and mean RMSE against the prediction step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    time = np.arange(1, len(run)) * TS
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True)
    for j, (ax, name) in enumerate(zip(axes, VEHICLE_STATES)):
        for label, trace in traces.items():
            ax.plot(time, trace[:, j], lw=0.8, label=label)
        symbol, unit = STATE_LABELS[name]
        ax.set_ylabel(f"{symbol} ({unit})")
        ax.grid(alpha=0.3)
    axes[0].set_title(f"One-step prediction errors on test run {run.name} (seed 0)")
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig6 = out_dir / "fig6_prediction_errors.png"
    fig.savefig(fig6, dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for j, (ax, name) in enumerate(zip(axes, VEHICLE_STATES)):
        for label, curve in horizons.items():
            steps = np.arange(1, curve.shape[0] + 1)
            ax.plot(steps, curve[:, j], lw=1.2, ls="-" if label.startswith("DK") else "--", label=label)
        ax.set_title(f"{name} RMSE ({STATE_LABELS[name][1]}), mean over seeds")
        ax.set_yscale("log")  # a diverging baseline (EDMDc) would flatten the others on a linear axis
        ax.set_xlabel("prediction step (25 ms)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    horizon_png = out_dir / "prediction_horizon_rmse.png"
    fig.savefig(horizon_png, dpi=120)
    plt.close(fig)
    return [fig6, horizon_png]


@dataclass
class Measured:
    """Table I's figures: rows {label, seeds: [figures per seed], rho, epochs, note, seed_ids},
    the mean RMSE per prediction step of each row (steps, 3), seed 0's one-step error traces of
    the learned rows (len(trace_run) - 1, 3) along its first test run ``trace_run``."""

    rows: list[dict]
    horizons: dict[str, np.ndarray]
    traces: dict[str, np.ndarray]
    trace_run: Trajectory
    data_hash: str


def measure_rows(data_dir: Path, rows: Sequence[Row], seeds: Sequence[int], models_dir: Path,
                 executor_options: dict[str, Any] | None = None) -> Measured:
    """Train the missing models of ``rows`` (:func:`train_missing`), then evaluate them and
    the rows without training (:func:`closed_form_rows`) per seed on its test runs. With no
    ``rows`` nothing is trained (and torch is not imported)."""
    runs = load_trajectories(data_dir, states=WHEEL_STATES)
    data_hash = dataset_hash(data_dir)
    if rows:
        models_dir.mkdir(parents=True, exist_ok=True)
        train_missing(rows, seeds, data_dir, data_hash, models_dir, executor_options)
    table: dict[str, dict] = {}
    curves: dict[str, list[np.ndarray]] = {}
    traces: dict[str, np.ndarray] = {}
    trace_run: Trajectory | None = None
    for seed in seeds:
        train_runs, _, test_runs = split_runs(runs, TrainingSettings(seed=seed))
        if trace_run is None:
            trace_run = test_runs[0]
        predictors: dict[str, tuple[Predictor, float | None, str, str | None]] = {}
        for row in rows:
            model = cached_model(row, seed, data_hash, models_dir)
            if model is None:
                raise KoopmanError(f"{row.label} seed {seed}: no model after training; delete {models_dir}")
            if model.metadata["split"]["test"] != [r.name for r in test_runs]:
                raise KoopmanError(f"{row.label} seed {seed}: the model's test runs differ from the split; "
                                   f"delete {models_dir}")
            epochs = f"{model.metadata['best_epoch']}/{model.metadata['epochs_run']}"
            predictors[row.label] = (VehicleStates(model, len(row.states)), model.spectral_radius(),
                                     f"{model.form} form, states {', '.join(row.states)}, n_z = {model.n_z}",
                                     epochs)
        for label, (predictor, rho, note) in closed_form_rows(runs, seed, train_runs, test_runs).items():
            predictors[label] = (predictor, rho, note, None)
        for label, (predictor, rho, note, epochs) in predictors.items():
            entry = table.setdefault(label, {"label": label, "seeds": [], "rho": None if rho is None else [],
                                             "epochs": [], "note": note, "seed_ids": []})
            entry["seeds"].append(evaluate(predictor, test_runs))
            entry["seed_ids"].append(seed)
            if rho is not None:
                entry["rho"].append(rho)
            if epochs is not None:
                entry["epochs"].append(epochs)
            curves.setdefault(label, []).append(horizon_curve(predictor, test_runs))
            if seed == seeds[0] and label.startswith("DK"):
                traces[label] = (predictor.predict(trace_run.states[:-1], trace_run.inputs[:-1, None, :])[:, 0]
                                 - trace_run.states[1:, :3])
        print(f"seed {seed}: evaluated {len(predictors)} models", flush=True)
    horizons = {label: np.mean(c, axis=0) for label, c in curves.items()}
    return Measured(list(table.values()), horizons, traces, trace_run, data_hash)


def table_json(measured: Measured, data_dir: Path, seeds: Sequence[int]) -> dict[str, Any]:
    """What ``table1.json`` holds (the rows, the data and seeds, the RMSE per step)."""
    return {"data_hash": measured.data_hash, "data_dir": str(data_dir), "seeds": list(seeds),
            "rows": measured.rows, "horizon_rmse": {k: v.tolist() for k, v in measured.horizons.items()}}


def build_table(data_dir: Path, rows: Sequence[Row], seeds: Sequence[int], models_dir: Path,
                out_dir: Path, executor_options: dict[str, Any] | None = None) -> list[dict]:
    """:func:`measure_rows`, then write table1.md / .json and the two figures into
    ``out_dir``. Returns the table rows."""
    measured = measure_rows(data_dir, rows, seeds, models_dir, executor_options)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "table1.md").write_text(markdown_table(measured.rows, data_dir))
    (out_dir / "table1.json").write_text(json.dumps(table_json(measured, data_dir, seeds), indent=1) + "\n")
    plot_figures(out_dir, measured.traces, measured.horizons, measured.trace_run)
    return measured.rows


def _indices(text: str) -> tuple[int, ...]:
    return tuple(int(v) for v in text.split(",") if v.strip())


def main(argv: Sequence[str] | None = None) -> int:
    from studies.campaign.executors import add_executor_arguments

    parser = argparse.ArgumentParser(prog="python -m studies.table1", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/wide"))
    parser.add_argument("--rows", type=_indices, default=tuple(range(len(ROWS))),
                        help="indices of ROWS, comma-separated: " + "; ".join(
                            f"{i} {r.label}" for i, r in enumerate(ROWS)))
    parser.add_argument("--seeds", type=_indices, default=SEEDS)
    parser.add_argument("--models-dir", type=Path, default=Path("build/table1"))
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    add_executor_arguments(parser)
    args = parser.parse_args(argv)
    try:
        if not args.data.is_dir():
            raise KoopmanError(f"data directory not found: {args.data} (run `make train`, which generates it)")
        bad = [i for i in args.rows if not 0 <= i < len(ROWS)]
        if bad or not args.seeds:
            raise KoopmanError(f"--rows must be indices 0..{len(ROWS) - 1} (got {bad}) and --seeds non-empty")
        build_table(args.data, [ROWS[i] for i in args.rows], args.seeds, args.models_dir, args.out,
                    dict(address=args.address, workers=args.workers, serial=args.serial))
    except (ModelError, HilError, OSError, ValueError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out / 'table1.md'}, {args.out / 'fig6_prediction_errors.png'}")
    return 0


if __name__ == "__main__":
    # Run the imported module's main: Ray workers import train_task from studies.table1.
    from studies.table1 import main as _main

    sys.exit(_main())

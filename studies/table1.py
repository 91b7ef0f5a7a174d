"""Table I: prediction errors of the learned model forms and of the physics models, over seeds.

The table's rows and seeds are the grid ``studies/campaign/grids/table1.toml`` (the
campaign engine's ``prediction`` runner, ``studies.campaign.prediction_grid``): the first
default model (speed-scheduled lift with the measured wheel angle in the state), the
scheduled form on [vx, vy, r] alone (what the wheel angle adds), the bilinear form with the
dictionary, the paper's linear form (eq. 5), and the mirror-symmetric form with its
steer-bilinear term, without and with the gain anchor (the latter the default,
``DEFAULT_ROW``, since issue 14's step steer), the default with the lateral velocity's
anchor as well (``--gain-anchor-vy``, issue 40, ``VY_ANCHOR_ROW``), and the mirror form with
d = 12 learned features on the physics dictionary (issue 40) without the gain anchor
(``DICTIONARY_ROW``), with it at weight 10 (``DICTIONARY_ANCHOR_ROW``) and at weight 1
(``DICTIONARY_LIGHT_ANCHOR_ROW``), and the last without the dictionary's vx^2/100
(``DICTIONARY_NO_SQUARE_ROW``), each trained (``ROWS``) with ``SEEDS`` (5
seeds: the seed draws the weights AND the train / validation / test split by run) on the
same data set (default ``data/wide``, the default artefact's). Beside them, fitted or built
on each seed's split (``CLOSED_FORM_ROWS``): DMDc, EDMDc (monomials), the trainer's
least-squares lifts ``--form edmdc-linear`` / ``edmdc-bilinear`` (the physics dictionary,
fitted by ``models.lifted_least_squares`` as the trainer fits them, on the trainer's default
states), LMPC's linear bicycle (speed held) and NMPC's single track (nominal parameters).
Every model is evaluated on its seed's held-out test runs: one-step RMSE, and open-loop RMSE
over 1 s (40 steps) and 2 s (80 steps) with the recorded inputs, of vx, vy and yaw rate; each
cell of the table is the mean +- the standard deviation over the seeds.

Each row x seed is one cell of the engine (``studies.campaign.prediction_cell``: train or
fit, then measure), run on the campaigns' executors (a local Ray with one worker per core by
default, ``--address`` for a cluster, ``--serial`` in this process) and cached in
``--models-dir`` (default ``build/table1/``): the trained models as ``*.npz`` (keyed by data
hash, settings and states; the default row's seed 0 reuses the committed artefact when it
matches), the measured cells as ``cache/<key>.json`` (keyed by row, seed, data hash and
code). Training all rows takes about an hour on 2 cores; the table can be built in several
sittings (the cache keeps what is done; ``--rows`` / ``--seeds`` select).

Writes ``results/table1.md``, ``results/table1.json``, ``results/fig6_prediction_errors.png``
(the first seed's one-step errors along its first test run, as the paper's Fig. 6) and
``results/prediction_horizon_rmse.png`` (RMSE against the prediction step, mean over seeds).
CLI: ``python -m studies.table1 [--data data/wide] [--rows 0,4] [--seeds 0,1,2,3,4]
[--address ADDR] [--workers N] [--serial]``. The closed-form rows alone, in minutes:
``studies/table1_least_squares.py`` (``make table1-lsq``).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from hil.errors import HilError
from models.errors import ModelError
from models.koopman import KoopmanError
from models.koopman_data import dataset_hash, load_trajectories, split_runs
from models.koopman_metrics import Trajectory
from models.koopman_settings import TrainingSettings
from studies.campaign.grid import load_grid
from studies.campaign.prediction_grid import PredictionGrid
from studies.campaign.prediction_rows import (  # noqa: F401 - Table I's names, where they always were
    HORIZONS, TRAIN_FIT, TS, VEHICLE_STATES, WHEEL_STATES, Row, VehicleStates, evaluate, horizon_curve)
from studies.campaign.prediction_training import (  # noqa: F401 - as above
    cached_model, cached_model_path, train_missing)

#: The grid of Table I's rows and seeds (``studies/campaign/grids/table1.toml``).
GRID = "table1"
STATE_LABELS = {"vx": ("E_x", "m/s"), "vy": ("E_y", "m/s"), "yaw_rate": ("E_r", "rad/s")}


def table1_grid(grid: str | Path = GRID) -> PredictionGrid:
    """Table I's grid (a ``prediction`` grid file or a shipped grid's name)."""
    loaded = load_grid(grid)
    if not isinstance(loaded, PredictionGrid):
        raise KoopmanError(f"{grid}: not a grid of the prediction runner (axes.runner = \"prediction\")")
    return loaded


_GRID = table1_grid()
SEEDS = tuple(dict.fromkeys(cell.seed for cell in _GRID.cells))   # in the grid's order
#: The trained rows (``--rows`` indexes them) and the rows without training, in table order.
ROWS = tuple(row for row in _GRID.rows.values() if row.fit == TRAIN_FIT)
CLOSED_FORM_ROWS = tuple(row for row in _GRID.rows.values() if row.fit != TRAIN_FIT)
#: The trainer's closed-form lifts as rows: label -> ``--form`` (models/lifted_least_squares.py).
LEAST_SQUARES_ROWS = {row.label: row.fit for row in CLOSED_FORM_ROWS if row.fit.startswith("edmdc-")}
#: The rows fitted by least squares (the others without training are physics models).
FITTED_ROWS = tuple(row.label for row in CLOSED_FORM_ROWS if row.fit not in ("bicycle", "single_track"))
#: The row of the committed default artefact (models/artifacts/dk_d5): its seed 0. The grid
#: marks it by its label's "(default)".
DEFAULT_ROW = next(row for row in ROWS if row.label.endswith("(default)"))
#: The default with the lateral velocity's anchor as well (issue 40): the row whose
#: training sets ``gain_anchor_vy``.
VY_ANCHOR_ROW = next(row for row in ROWS if row.overrides.get("gain_anchor_vy"))
#: The mirror form with the physics dictionary as a fixed part of its lift (issue 40),
#: without the gain anchor, with it at the default's weight 10 and at weight 1.
DICTIONARY_ROW = next(row for row in ROWS if row.overrides.get("mirror_symmetric") and row.overrides.get("dictionary")
                      and not row.overrides.get("gain_anchor"))
DICTIONARY_ANCHOR_ROW = next(row for row in ROWS
                             if row.overrides.get("dictionary") and row.overrides.get("gain_anchor") == 10.0)
DICTIONARY_LIGHT_ANCHOR_ROW = next(row for row in ROWS if "vx^2/100" in row.overrides.get("dictionary", ())
                                   and row.overrides.get("gain_anchor") == 1.0)
#: The weight-1 row without the dictionary's vx^2/100 (issue 40: with it the speed drifts
#: with the torque on make identify's log, docs/identification.md).
DICTIONARY_NO_SQUARE_ROW = next(row for row in ROWS if row.overrides.get("dictionary")
                                and "vx^2/100" not in row.overrides["dictionary"]
                                and row.overrides.get("gain_anchor") == 1.0)


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
    the mean RMSE per prediction step of each row (steps, 3), the first seed's one-step error
    traces of the learned rows (len(trace_run) - 1, 3) along its first test run ``trace_run``."""

    rows: list[dict]
    horizons: dict[str, np.ndarray]
    traces: dict[str, np.ndarray]
    trace_run: Trajectory
    data_hash: str


def table_grid(rows: Sequence[Row], seeds: Sequence[int], data_dir: Path,
               grid: PredictionGrid | None = None) -> PredictionGrid:
    """The cells of the table: the trained ``rows`` and ``grid``'s rows without training
    (default grid: Table I's) x ``seeds``, on the data set in ``data_dir``."""
    grid = grid or _GRID
    return grid.with_rows([*rows, *(row for row in grid.rows.values() if row.fit != TRAIN_FIT)], seeds, data_dir)


def run_cells(grid: PredictionGrid, models_dir: Path, executor_options: dict[str, Any] | None = None) -> list[dict]:
    """Every cell of ``grid`` on the campaign engine (``studies.campaign.runner``): cached in
    ``models_dir`` (the trained models beside ``cache/``), the others on the executor of
    ``executor_options`` (none is started when every cell is cached). Returns the cell rows
    in grid order.

    Raises:
        KoopmanError: naming every cell that failed (the others are cached).
        KeyboardInterrupt: interrupted (the finished cells are cached).
    """
    from studies.campaign.executors import SerialExecutor, open_executor
    from studies.campaign.runner import cached_rows, cell_task, run_campaign

    task = cell_task(grid)
    models_dir.mkdir(parents=True, exist_ok=True)
    done = len(cached_rows(grid, models_dir)) == len(grid.cells)
    executor = SerialExecutor(task) if done else open_executor(task, **(executor_options or {}))
    try:
        result = run_campaign(grid, models_dir, executor)
    finally:
        executor.close()
    if result.interrupted:
        raise KeyboardInterrupt
    failures = [f"{row['row']} seed {row['seed']}: {row.get('error') or 'no result'}"
                for row in result.rows if not row.get("completed")]
    if failures:
        raise KoopmanError("cells failed (the others are cached): " + "; ".join(failures))
    return result.rows


def measure_rows(data_dir: Path, rows: Sequence[Row], seeds: Sequence[int], models_dir: Path,
                 executor_options: dict[str, Any] | None = None, grid: PredictionGrid | None = None) -> Measured:
    """Measure the trained ``rows`` and the rows without training x ``seeds`` as cells of
    :func:`table_grid` (:func:`run_cells`: the missing models trained first, each seed's
    rows evaluated on its test runs), and gather the cells into the table's rows."""
    grid = table_grid(rows, seeds, data_dir, grid)
    cells = {(row["row"], row["seed"]): row for row in run_cells(grid, models_dir, executor_options)}
    table: list[dict] = []
    horizons: dict[str, np.ndarray] = {}
    traces: dict[str, np.ndarray] = {}
    for label in grid.rows:
        per_seed = [cells[(label, seed)] for seed in seeds]
        first = per_seed[0]
        table.append({"label": label, "seeds": [cell["figures"] for cell in per_seed],
                      "rho": None if first["rho"] is None else [c["rho"] for c in per_seed if c["rho"] is not None],
                      "epochs": [c["epochs"] for c in per_seed if c["epochs"] is not None],
                      "note": first["note"], "seed_ids": list(seeds)})
        horizons[label] = np.mean([np.asarray(cell["horizon_rmse"]) for cell in per_seed], axis=0)
        if label.startswith("DK"):
            traces[label] = np.asarray(first["trace"])
    runs = load_trajectories(data_dir, states=WHEEL_STATES)
    trace_run = split_runs(runs, TrainingSettings(seed=seeds[0]))[2][0]
    return Measured(table, horizons, traces, trace_run, dataset_hash(data_dir))


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
                        help="indices of the trained rows, comma-separated: " + "; ".join(
                            f"{i} {r.label}" for i, r in enumerate(ROWS)))
    parser.add_argument("--seeds", type=_indices, default=SEEDS)
    parser.add_argument("--models-dir", type=Path, default=Path("build/table1"),
                        help="the trained models and the cells' cache (cache/)")
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
    sys.exit(main())

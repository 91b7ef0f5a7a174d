"""Issue 40, item 3 on the identification log: the deep models beside the trainer's
least-squares lifts, over seeds.

On the one log of the identification drive (``build/identification/drive_changed.log``,
``make identify``) each deep form of ``DEEP_FORMS`` is trained for each seed, one training
at a time, each cached in ``build/identification_lsq/`` under a key of the log's and
vehicle file's contents, the seed and the options, so a rerun reuses it:

- the model as ``make identify`` trains it (``python -m models.koopman_train --logs LOG --out
  DIR --replace --vehicle FILE``: the default form, the default settings);
- Table I's candidate for the next default (issue 40): the mirror form with d = 12 learned
  features (3 even) on the physics dictionary, the servo lag, the steer-bilinear term and the
  gain anchor at weight 1 (``CANDIDATE_OPTIONS``, the trainer's options of Table I's row
  ``studies.table1.DICTIONARY_LIGHT_ANCHOR_ROW``);
- the same without the dictionary's vx^2/100 (``NO_SQUARE_OPTIONS``, Table I's row
  ``studies.table1.DICTIONARY_NO_SQUARE_ROW``), with which the speed drifts less with the
  torque on this log.

Seed 0 of the first form draws the split by run exactly as ``make identify`` does; every
other model, the closed-form lifts (``--form edmdc-linear``, ``--form edmdc-bilinear``,
seconds) included, is given that split (``--val-runs`` / ``--test-runs``), so every model is
measured on the same held-out test pieces (checked on each artefact's metadata: a model
naming other test pieces is refused).

The figures are Table I's (``studies.campaign.prediction_rows.evaluate``): open-loop RMSE
over 1 s (40 steps) and 2 s (80 steps) of vx, vy and yaw rate with the recorded inputs on the
test pieces; each deep form as mean and min/max over the seeds, and for vy and yaw rate the
ratio deep mean / best least-squares lift against the issue's goal (at most 0.9).

A second table gives the same figures on the test pieces' stretches whose every state lies
within the training pieces' range (``models.range_coverage``), and names the samples beyond
it: one test piece of the log drives below the slowest training sample, where a learned lift
extrapolates and a fixed dictionary fitted by least squares does so more gracefully.

Writes ``least_squares.md`` and ``.json`` into ``--out``. CLI: ``python -m
studies.identification_least_squares --log LOG --vehicle FILE --out DIR [--seeds 0,1,2,3,4]
[--replace] [--work build/identification_lsq]`` (``make identify-lsq``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.errors import KoopmanError, ModelError
from studies.provenance import file_digest
from studies.table1 import DICTIONARY_LIGHT_ANCHOR_ROW, DICTIONARY_NO_SQUARE_ROW

REPO = Path(__file__).resolve().parents[1]
#: The least-squares lifts of the trainer, fitted in closed form from the same log.
LEAST_SQUARES_FORMS = ("edmdc-linear", "edmdc-bilinear")
#: The states and horizons of the issue's goal (issue 40, item 3).
COMPARED_STATES = ("vy", "yaw_rate")
REPORTED_STATES = ("vx", "vy", "yaw_rate")
HORIZONS = ("1 s", "2 s")
#: The issue's goal: deep mean / best least-squares lift at most this.
GOAL_RATIO = 0.9
DEFAULT_SEEDS = (0, 1, 2, 3, 4)
STEM = "least_squares"
#: The trainer's default sample time (its --ts), the one make identify trains at.
TS = 0.025
DEEP_LABEL = "deep (make identify's default form)"
#: Training settings of a Table I row -> the trainer's option (``models/koopman_cli.py``), in
#: the order the options are written (the models' cache key depends on it).
TRAINER_FLAGS = {"mirror_symmetric": "--mirror-symmetric", "n_features": "--features",
                 "even_features": "--even-features", "servo_lag": "--servo-lag",
                 "steer_bilinear": "--steer-bilinear", "dictionary": "--dictionary", "gain_anchor": "--gain-anchor"}


def trainer_options(overrides: dict[str, Any]) -> tuple[str, ...]:
    """The trainer's command-line options of a Table I row's training settings.

    Raises:
        KoopmanError: a setting without an option in ``TRAINER_FLAGS``.
    """
    unknown = sorted(set(overrides) - set(TRAINER_FLAGS))
    if unknown:
        raise KoopmanError(f"no trainer option for the settings {', '.join(unknown)}")
    options: list[str] = []
    for name, flag in TRAINER_FLAGS.items():
        if name not in overrides:
            continue
        value = overrides[name]
        if isinstance(value, bool):
            options += [flag] if value else []
        elif isinstance(value, tuple):
            options += [flag, ",".join(value)]
        else:
            options += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    return tuple(options)


#: The trainer's options of Table I's candidate row (issue 40), taken from the row itself
#: (``studies.table1.DICTIONARY_LIGHT_ANCHOR_ROW``, studies/campaign/grids/table1.toml): the
#: d = 12 mirror form on the physics dictionary with the gain anchor at weight 1.
CANDIDATE_OPTIONS = trainer_options(DICTIONARY_LIGHT_ANCHOR_ROW.overrides)
CANDIDATE_LABEL = "deep, d=12 mirror form on the physics dictionary + gain anchor (w = 1)"
#: The same without the dictionary's vx^2/100 (``studies.table1.DICTIONARY_NO_SQUARE_ROW``).
NO_SQUARE_OPTIONS = trainer_options(DICTIONARY_NO_SQUARE_ROW.overrides)
NO_SQUARE_LABEL = "deep, the same without the dictionary's vx^2/100"
#: (label, cache prefix, the trainer's options besides seed, threads and split), make
#: identify's own form first (its seed 0 draws the split every other model is given).
DEEP_FORMS = ((DEEP_LABEL, "deep", ()), (CANDIDATE_LABEL, "dictionary", CANDIDATE_OPTIONS),
              (NO_SQUARE_LABEL, "no-square", NO_SQUARE_OPTIONS))


def cache_key(log_sha256: str, vehicle_sha256: str, options: Sequence[str]) -> str:
    """12 hex digits naming a model: the log's and vehicle file's contents and the trainer's
    options (seed and split included)."""
    text = json.dumps({"log": log_sha256, "vehicle": vehicle_sha256, "options": list(options)})
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def split_options(split: dict[str, list[str]] | None) -> list[str]:
    """``--val-runs`` / ``--test-runs`` of a split (``None``: none, the seed draws it)."""
    if split is None:
        return []
    return ["--val-runs", ",".join(split["validation"]), "--test-runs", ",".join(split["test"])]


def train_cached(log: Path, vehicle: Path, work: Path, label: str, options: Sequence[str],
                 digests: tuple[str, str], replace: bool = False) -> Path:
    """The folder of the model ``python -m models.koopman_train --logs LOG --out DIR --replace
    --no-progress --vehicle FILE [OPTIONS]`` writes, trained in its own process unless
    ``work`` already holds it under its key (``replace``: train again).

    Raises:
        KoopmanError: the training failed.
    """
    folder = work / f"{label}-{cache_key(*digests, options)}"
    if (folder / "koopman.json").is_file() and (folder / "koopman.npz").is_file() and not replace:
        print(f"{label}: reusing {folder}", flush=True)
        return folder
    work.mkdir(parents=True, exist_ok=True)
    argv = ["--logs", str(log), "--out", str(folder), "--replace", "--no-progress", "--vehicle", str(vehicle),
            *options]
    print(f"{label}: python -m models.koopman_train {' '.join(argv)}", flush=True)
    started = time.perf_counter()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-m", "models.koopman_train", *argv], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if done.returncode != 0:
        raise KoopmanError(f"{label}: training from {log} failed (exit status {done.returncode}):\n"
                           + done.stdout[-2000:])
    print(f"{label}: done in {time.perf_counter() - started:.0f} s -> {folder}", flush=True)
    return folder


def read_split(folder: Path) -> dict[str, list[str]]:
    """The split by run an artefact's metadata records (``koopman.json``)."""
    meta = json.loads((folder / "koopman.json").read_text())
    return {role: list(meta["split"][role]) for role in ("train", "validation", "test")}


def check_same_test_pieces(splits: dict[str, dict[str, list[str]]]) -> list[str]:
    """The test pieces every model's metadata names (sorted), ``splits``: label -> split.

    Raises:
        KoopmanError: naming the models whose test pieces differ from the first one's.
    """
    if not splits:
        raise KoopmanError("no model to compare")
    first_label, first = next(iter(splits.items()))
    reference = sorted(first["test"])
    differing = [f"{label}: {sorted(split['test'])}" for label, split in splits.items()
                 if sorted(split["test"]) != reference]
    if differing:
        raise KoopmanError(f"the models were not tested on the same pieces ({first_label}: {reference}; "
                           + "; ".join(differing) + "): refusing to compare them")
    return reference


def measure(folder: Path, test_runs: Sequence[Any]) -> dict[str, dict[str, float]]:
    """Table I's figures of the artefact in ``folder`` on ``test_runs``: {state: {one_step_rmse,
    1 s, 2 s}} over vx, vy, yaw rate."""
    from models.koopman import KoopmanModel
    from studies.campaign.prediction_rows import VehicleStates, evaluate

    model = KoopmanModel.load(folder / "koopman.json")
    return evaluate(VehicleStates(model, len(model.state_names)), test_runs)


def summarise(deep: dict[str, Sequence[dict]], least_squares: dict[str, dict]) -> dict[str, Any]:
    """The table's cells and the goal's ratios.

    ``deep``: deep form's label -> per seed {state: {horizon: rmse}}; ``least_squares``:
    form -> {state: {horizon: rmse}}. Returns {rows: [{label, seeds, figures: per state and
    horizon {mean, min, max}}], goals: [{model, state, horizon, deep_mean, deep_min, deep_max,
    best_least_squares, least_squares, ratio, goal, met}]}, the deep forms in ``deep``'s order.
    """
    if not deep or not all(deep.values()):
        raise KoopmanError("no deep model to summarise")
    rows = [{"label": label, "seeds": len(seeds), "figures": {
        state: {horizon: {"mean": float(np.mean([f[state][horizon] for f in seeds])),
                          "min": float(np.min([f[state][horizon] for f in seeds])),
                          "max": float(np.max([f[state][horizon] for f in seeds]))}
                for horizon in HORIZONS} for state in REPORTED_STATES}} for label, seeds in deep.items()]
    goals = []
    for row in rows:
        for state in COMPARED_STATES:
            for horizon in HORIZONS:
                best = min(least_squares, key=lambda form: least_squares[form][state][horizon])
                cell = row["figures"][state][horizon]
                ratio = cell["mean"] / least_squares[best][state][horizon]
                goals.append({"model": row["label"], "state": state, "horizon": horizon, "deep_mean": cell["mean"],
                              "deep_min": cell["min"], "deep_max": cell["max"], "best_least_squares": best,
                              "least_squares": least_squares[best][state][horizon], "ratio": ratio,
                              "goal": GOAL_RATIO, "met": bool(ratio <= GOAL_RATIO)})
    for form, figures in least_squares.items():
        rows.append({"label": form, "seeds": None, "figures": {
            state: {horizon: {"mean": float(figures[state][horizon])} for horizon in HORIZONS}
            for state in REPORTED_STATES}})
    return {"rows": rows, "goals": goals}


def markdown(summary: dict[str, Any], log: Path, seeds: Sequence[int], test_pieces: Sequence[str],
             within: dict[str, Any] | None = None) -> str:
    """The report: the table, then a sentence per goal; then, when ``within`` is given
    ({"summary", "outside", "training_min", "training_max", "within_samples", "test_samples"}), the
    same on the test pieces' stretches within the training pieces' states."""
    lines = ["# The deep models beside the least-squares lifts, on the identification log", "",
             "Generated by `make identify-lsq` (`python -m studies.identification_least_squares`). "
             f"Log `{log}`; the deep model trained as `make identify` trains it and Table I's candidate "
             "for the next default (trainer options "
             f"`{' '.join(CANDIDATE_OPTIONS)}`) and the same without the dictionary's vx^2/100 (Table I's "
             f"eleventh row, `{' '.join(NO_SQUARE_OPTIONS)}`), seeds {', '.join(map(str, seeds))} "
             f"({len(seeds)} seed{'s' if len(seeds) != 1 else ''}); the lifts `--form edmdc-linear` / "
             "`edmdc-bilinear` fitted in closed form from the same log. Every model on the same held-out test "
             f"pieces: {', '.join(test_pieces)}.", "",
             "Open-loop RMSE with the recorded inputs (1 s = 40 steps, 2 s = 80 steps); each deep model's mean "
             "over the seeds, with [min, max].", ""]
    lines += _table_lines(summary)
    if within is not None:
        lines += ["## Within the training pieces' states", "",
                  "The test pieces' samples beyond the range of the training pieces' states "
                  "(`models.range_coverage`; there the figures above measure extrapolation):", ""]
        lines += [f"- {e['run']}: {e['samples']} of {e['of']} samples with {e['state']} outside "
                  f"{within['training_min'][e['state']]:.4g} .. {within['training_max'][e['state']]:.4g} "
                  f"(the piece's {e['low']:.4g} .. {e['high']:.4g})" for e in within["outside"]] or ["- none"]
        lines += ["", f"The same figures on the test pieces' stretches whose every state lies within that range "
                      f"({within['within_samples']} of {within['test_samples']} samples):", ""]
        lines += _table_lines(within["summary"])
    return "\n".join([*lines, ""])


def _table_lines(summary: dict[str, Any]) -> list[str]:
    """The figures' table of ``summary`` and a sentence per goal."""
    n_seeds = summary["rows"][0]["seeds"]
    lines = []
    head = [f"{h} {s}" for h in HORIZONS for s in REPORTED_STATES]
    lines += ["| model | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for row in summary["rows"]:
        cells = []
        for horizon in HORIZONS:
            for state in REPORTED_STATES:
                cell = row["figures"][state][horizon]
                text = f"{cell['mean']:.4f}"
                if "min" in cell:
                    text += f" [{cell['min']:.4f}, {cell['max']:.4f}]"
                cells.append(text)
        label = row["label"] + (f", {row['seeds']} seeds" if row["seeds"] else "")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", f"Issue 40's goal: deep mean / best least-squares lift at most {GOAL_RATIO} "
                  f"(over {n_seeds} seed{'s' if n_seeds != 1 else ''}).", ""]
    for model in dict.fromkeys(goal["model"] for goal in summary["goals"]):
        lines.append(f"{model}:")
        lines.append("")
        for goal in (g for g in summary["goals"] if g["model"] == model):
            verdict = "met" if goal["met"] else "NOT met"
            lines.append(f"- {goal['state']}, {goal['horizon']}: deep {goal['deep_mean']:.4f} / "
                         f"{goal['best_least_squares']} {goal['least_squares']:.4f} = {goal['ratio']:.2f}: {verdict}.")
        lines.append("")
    return lines


def within_training_range(folders: dict[str, Path], by_name: dict[str, Any], test_runs: Sequence[Any],
                          seeds: Sequence[int]) -> dict[str, Any]:
    """Every model's figures on the test pieces' stretches within the training pieces' state
    range (every model has the same split: ``check_same_test_pieces``), summarised as the
    main table is: ``models.range_coverage.range_split``'s figures plus {summary, figures}."""
    from models.range_coverage import range_split

    train_runs = [by_name[name] for name in read_split(folders[next(iter(folders))])["train"]]
    coverage, stretches = range_split(train_runs, test_runs)
    figures = {label: measure(folder, stretches) for label, folder in folders.items()}
    deep = {label: [figures[f"{prefix} seed {seed}"] for seed in seeds] for label, prefix, _ in DEEP_FORMS}
    return {**coverage, "summary": summarise(deep, {form: figures[form] for form in LEAST_SQUARES_FORMS}),
            "figures": figures}


def _seeds(text: str) -> tuple[int, ...]:
    try:
        seeds = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seeds: comma-separated integers expected, got {text!r}") from None
    if not seeds:
        raise argparse.ArgumentTypeError("--seeds must name at least one seed")
    return seeds


def run_study(log: Path, vehicle: Path, out: Path, seeds: Sequence[int], work: Path,
              replace: bool = False) -> list[Path]:
    """Train / fit / measure / write (module docstring); returns the files written."""
    from models.log_identification import load_log_runs

    for path, option in ((log, "--log"), (vehicle, "--vehicle")):
        if not path.is_file():
            hint = " (make identify records it)" if option == "--log" else ""
            raise KoopmanError(f"{option} {path}: file not found{hint}")
    if not out.parent.is_dir() and out.parent != Path(""):
        raise KoopmanError(f"--out {out}: folder {out.parent} does not exist")
    digests = (file_digest(log), file_digest(vehicle))  # both checked to exist above
    threads = ["--threads", "1"]
    folders: dict[str, Path] = {}
    # make identify's form, seed 0, draws the split as make identify does; every other model is given it
    ordered = sorted(seeds, key=lambda seed: seed != 0)
    split = None
    total = len(ordered) * len(DEEP_FORMS)
    for form_index, (label, prefix, options) in enumerate(DEEP_FORMS):
        for done, seed in enumerate(ordered):
            given = None if (form_index == 0 and seed == 0) else split
            print(f"[{form_index * len(ordered) + done + 1}/{total}] {label}, seed {seed}", flush=True)
            folder = train_cached(log, vehicle, work, f"{prefix}-seed{seed}",
                                  [*options, "--seed", str(seed), *threads, *split_options(given)], digests, replace)
            folders[f"{prefix} seed {seed}"] = folder
            split = split or read_split(folder)
    for form in LEAST_SQUARES_FORMS:
        folders[form] = train_cached(log, vehicle, work, form, ["--form", form, *split_options(split)],
                                     digests, replace)
    test_pieces = check_same_test_pieces({label: read_split(folder) for label, folder in folders.items()})
    runs, _, _, _ = load_log_runs([log], TS, "command", None, None)
    by_name = {run.name: run for run in runs}
    test_runs = [by_name[name] for name in read_split(folders[next(iter(folders))])["test"]]
    figures = {label: measure(folder, test_runs) for label, folder in folders.items()}
    deep = {label: [figures[f"{prefix} seed {seed}"] for seed in ordered] for label, prefix, _ in DEEP_FORMS}
    summary = summarise(deep, {form: figures[form] for form in LEAST_SQUARES_FORMS})
    within = within_training_range(folders, by_name, test_runs, ordered)
    out.mkdir(exist_ok=True)
    written = [out / f"{STEM}.md", out / f"{STEM}.json"]
    written[0].write_text(markdown(summary, log, ordered, test_pieces, within))
    written[1].write_text(json.dumps({"log": str(log), "log_sha256": digests[0], "vehicle": str(vehicle),
                                      "seeds": list(ordered), "test_pieces": test_pieces,
                                      "horizon_steps": {"1 s": 40, "2 s": 80},
                                      "models": {label: str(folder) for label, folder in folders.items()},
                                      "figures": figures, **summary, "within_training_range": within},
                                     indent=1) + "\n")
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.identification_least_squares",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--log", type=Path, required=True, help="the identification drive's CAN log")
    parser.add_argument("--vehicle", type=Path, required=True, help="its vehicle file (as make identify gives it)")
    parser.add_argument("--out", type=Path, required=True, help="folder for least_squares.md/.json")
    parser.add_argument("--seeds", type=_seeds, default=DEFAULT_SEEDS, help="seeds of each deep form (default 0,1,2,3,4)")
    parser.add_argument("--work", type=Path, default=Path("build/identification_lsq"),
                        help="cache of the trained models, keyed by seed and settings")
    parser.add_argument("--replace", action="store_true", help="train and fit again, ignoring the cache")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    args = parser.parse_args(argv)
    try:
        written = run_study(args.log, args.vehicle, args.out, args.seeds, args.work, args.replace)
    except (ModelError, OSError, ValueError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(written[0].read_text())
    print(f"wrote {', '.join(map(str, written))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``--compare-with OTHER.json`` of the trainer (``python -m models.koopman_train``): the model
just trained beside another one. numpy only, like the command line (``models/koopman_cli.py``).

Two uses, told apart by the other artefact's training ``settings`` and test runs:

- the same settings and test runs (``make train`` retraining the committed artefact): a
  reproduction check, every test figure within 10 % of the figures the other JSON records
  (exit 3 if not; only the JSON is needed, ``compare_test_errors``);
- other settings or test runs (another form, a least-squares lift, another seed): the other
  model (``OTHER.npz`` beside the JSON) runs on this training's test runs and both models'
  one-step and open-loop RMSE are printed side by side, so the two compare run for run
  (``compare_on_test_runs``). Where the other model was fitted on some of these runs, or
  on other data, a note says so.

The other artefact is read and checked before any training (``load_reference``): readable,
bounded, and of the data's states, inputs and sample time.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from models.errors import KoopmanError
from models.input_files import MODEL_FILE_MAX_BYTES, read_bounded
from models.koopman import KoopmanModel
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors

#: Largest relative change of a test figure a reproduction may show.
REPRODUCTION_TOLERANCE = 0.10
#: The figures printed side by side (Table I's RMSEs).
SIDE_BY_SIDE = ("one_step_rmse", "open_loop_rmse")


@dataclass(frozen=True)
class Reference:
    """The other artefact: its path, its JSON and, where its ``.npz`` is beside it, the model."""

    path: Path
    meta: dict[str, Any]
    model: KoopmanModel | None


def load_reference(path: Path, runs: Sequence[Trajectory], ts: float) -> Reference:
    """Read ``path`` (an artefact's JSON) and, when present, its model, for data ``runs`` at
    ``ts`` s: before any training, so a reference that cannot be compared costs no training.

    Raises:
        KoopmanError: naming ``--compare-with`` and the file: unreadable, not an artefact's
            JSON, or of other states, inputs or sample time than the data.
    """
    path = Path(path)
    try:
        meta = json.loads(read_bounded(path, MODEL_FILE_MAX_BYTES, KoopmanError))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise KoopmanError(f"--compare-with {path}: not a readable artefact JSON: {error}") from error
    if not isinstance(meta, dict) or not {"state_names", "input_names", "ts", "test_errors"} <= set(meta):
        raise KoopmanError(f"--compare-with {path}: not an artefact JSON (state_names, input_names, ts "
                           "and test_errors expected)")
    states, inputs = list(runs[0].state_names), list(runs[0].input_names)
    if (meta["state_names"], meta["input_names"]) != (states, inputs) or float(meta["ts"]) != float(ts):
        raise KoopmanError(f"--compare-with {path}: a model of states {meta['state_names']}, inputs "
                           f"{meta['input_names']} and ts {meta['ts']} s cannot run on these data (states "
                           f"{states}, inputs {inputs}, ts {ts} s)")
    model = KoopmanModel.load(path) if path.with_suffix(".npz").is_file() else None
    return Reference(path, meta, model)


def compare_with_reference(meta: dict[str, Any], test_runs: Sequence[Trajectory], reference: Reference) -> int:
    """Print the comparison of the model just trained (its artefact ``meta``, its test runs
    ``test_runs``) with ``reference``; returns the exit code (3: a reproduction outside the
    tolerance, else 0)."""
    settings, other_settings = meta.get("settings", {}), reference.meta.get("settings", {})
    same_test_runs = reference.meta.get("split", {}).get("test") == meta["split"]["test"]
    if other_settings == settings and same_test_runs:
        return 0 if compare_test_errors(meta["test_errors"], reference.meta["test_errors"], reference.path) else 3
    changed = sorted(k for k in set(other_settings) | set(settings) if other_settings.get(k) != settings.get(k))
    if "form" in changed:   # a least-squares lift records other settings than a network: name the form only
        differs = f"its form {other_settings.get('form')}, this one {settings.get('form')}"
    elif changed:
        differs = f"its training settings differ: {', '.join(changed)}"
    else:
        differs = "its test runs differ"
    if reference.model is None:
        print(f"not compared with {reference.path} ({differs}): there is no "
              f"{reference.path.with_suffix('.npz').name} beside it to run on this training's test runs")
        return 0
    print(f"compared with {reference.path} ({differs}) on this training's {len(test_runs)} test run(s):")
    for line in compare_on_test_runs(meta, test_runs, reference):
        print(line)
    return 0


def compare_on_test_runs(meta: dict[str, Any], test_runs: Sequence[Trajectory], reference: Reference) -> list[str]:
    """Lines of the side-by-side table: per state, this model's and the reference model's
    one-step RMSE and ``OPEN_LOOP_STEPS``-step open-loop RMSE on ``test_runs``, and notes
    where the reference saw these runs in its fitting or came from other data."""
    other = prediction_errors(reference.model, test_runs, OPEN_LOOP_STEPS)
    width = max(10, *(len(name) for name in meta["test_errors"]))
    lines = [f"  {'state':>{width}} {'figure':<28} {'this model':>11} {'other':>11} {'ratio':>7}"]
    for name, figures in meta["test_errors"].items():
        for key in SIDE_BY_SIDE:
            label = f"{key} ({OPEN_LOOP_STEPS} steps)" if key == "open_loop_rmse" else key
            ratio = figures[key] / max(other[name][key], 1e-12)
            lines.append(f"  {name:>{width}} {label:<28} {figures[key]:>11.5f} {other[name][key]:>11.5f} "
                         f"{ratio:>7.2f}")
    split = reference.meta.get("split", {})
    seen = sorted({r.name for r in test_runs} & {*split.get("train", []), *split.get("validation", [])})
    if _data_identity(meta) != _data_identity(reference.meta):
        lines.append(f"note: {reference.path} was fitted on other data ({_data_identity(reference.meta)}; "
                     f"these: {_data_identity(meta)})")
    elif seen:
        lines.append(f"note: {reference.path} was fitted on {len(seen)} of these test runs ({', '.join(seen)}): "
                     "its figures there are not held out (the same --seed and fractions, or --test-runs, "
                     "give both trainings one split)")
    return lines


def _data_identity(meta: dict[str, Any]) -> Any:
    """What names an artefact's data: the data set's hash, or the logs it was read from."""
    return meta.get("data_hash") or meta.get("logs")


def compare_test_errors(test_errors: dict, reference_errors: dict, reference_path: Path,
                        tolerance: float = REPRODUCTION_TOLERANCE) -> bool:
    """Print the relative change of every test figure against the reference's recorded
    ``test_errors`` (of the artefact JSON ``reference_path``).

    Returns True when all are within ``tolerance`` (relative).
    """
    worst = 0.0
    for name, figures in test_errors.items():
        for key, value in figures.items():
            ref = reference_errors[name][key]
            change = abs(value - ref) / max(abs(ref), 1e-12)
            worst = max(worst, change)
            print(f"  {name:>10} {key:<21} {value:.5f} vs {ref:.5f} ({100 * change:+.1f} %)")
    ok = worst <= tolerance
    print(f"largest relative change vs {reference_path}: {100 * worst:.1f} % "
          f"({'within' if ok else 'OUTSIDE'} {100 * tolerance:.0f} %)")
    return ok

"""The data of a deep Koopman training, torch-free: data sets read as trajectories and named
by their hash, runs split by run into train / validation / test, and the min-max bounds
fitted on the training runs (``MinMaxScaling``, the normalisation of the network).

The DMDc builder (``models/dmdc_artifact.py``) and the studies read their data through the
same functions; the windows the network trains on are ``models/koopman_train_windows.py``.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Sequence

import numpy as np

from models.koopman import DICTIONARY_STATES, KoopmanError, MinMaxScaling, dictionary_features
from models.koopman_metrics import Trajectory
from models.koopman_settings import DEFAULT_INPUTS, TrainingSettings


# ---------------------------------------------------------------------- runs
def split_runs(
    runs: Sequence[Trajectory], settings: TrainingSettings
) -> tuple[list[Trajectory], list[Trajectory], list[Trajectory]]:
    """Train / validation / test split by run (never by sample).

    Runs named in ``settings.test_runs`` / ``val_runs`` go there; a set not named is drawn
    from the other runs by its fraction of all runs (at least one), shuffled by the seed;
    the rest train. Without names the split is the one of every artefact so far.

    Raises:
        KoopmanError: fewer than 3 runs, a named run that is not in the data, or no run
            left to train on.
    """
    if len(runs) < 3:
        raise KoopmanError(
            f"need at least 3 runs to split train / validation / test by run, got {len(runs)}"
        )
    ordered = sorted(runs, key=lambda r: r.name)
    names = [r.name for r in ordered]
    unknown = sorted(n for n in set(settings.val_runs) | set(settings.test_runs) if n not in names)
    if unknown:
        raise KoopmanError(f"--val-runs / --test-runs name run(s) not in the data: {unknown} (runs: {names})")
    if not settings.val_runs and not settings.test_runs:
        order = np.random.default_rng(settings.seed).permutation(len(ordered))
        n_test = max(1, round(settings.test_fraction * len(runs)))
        n_val = max(1, round(settings.val_fraction * len(runs)))
        test = [ordered[i] for i in order[:n_test]]
        val = [ordered[i] for i in order[n_test : n_test + n_val]]
        train = [ordered[i] for i in order[n_test + n_val :]]
        return train, val, test
    named = set(settings.val_runs) | set(settings.test_runs)
    free = [r for r in ordered if r.name not in named]
    order = list(np.random.default_rng(settings.seed).permutation(len(free)))
    picked: dict[str, list[Trajectory]] = {}
    for role, chosen, fraction in (("test", settings.test_runs, settings.test_fraction),
                                   ("validation", settings.val_runs, settings.val_fraction)):
        if chosen:
            picked[role] = [r for r in ordered if r.name in chosen]
        else:
            count = max(1, round(fraction * len(runs)))
            picked[role] = [free[i] for i in order[:count]]
            order = order[count:]
    used = {r.name for group in picked.values() for r in group}
    train = [r for r in ordered if r.name not in used]
    if not train:
        raise KoopmanError(f"no run left to train on: validation {[r.name for r in picked['validation']]}, "
                           f"test {[r.name for r in picked['test']]}")
    return train, picked["validation"], picked["test"]


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
    """Named-column CSV runs (``models.dataset.load_dataset``) -> trajectories.

    Every one of ``inputs`` is held between samples when resampled to ``ts``, whatever its
    name (a throttle and a brake as the torque and the steer); the states are interpolated.
    """
    from models.dataset import load_dataset  # the CSV reader belongs to the data package

    columns = ("time", *states, *inputs)
    runs = load_dataset(directory, ts=ts, columns=columns, held=tuple(inputs))
    return [Trajectory(run.name, run.array(list(states)), run.array(list(inputs)), tuple(states), tuple(inputs))
            for run in runs]

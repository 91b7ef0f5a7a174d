"""Whether the test runs stay within the states the model was trained on.

A learned model's test figures mean what they say only where the test data lie within the
training data: beyond the training states (a speed below the slowest training sample, say)
they measure extrapolation, which a learned lift may do badly while a fixed dictionary
fitted by least squares does it gracefully. ``make identify``'s log has one such test piece
(docs/identification.md). This module says which test samples lie outside the training
data's state range and gives the test figures again on the stretches that lie within it,
so the trainer's report (``models.koopman_cli``) and the studies can show both.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from models.koopman_metrics import OPEN_LOOP_STEPS, Predictor, Trajectory, prediction_errors


def state_range(runs: Sequence[Trajectory]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (n_x,): the smallest and largest value of each state over ``runs``."""
    states = np.concatenate([run.states for run in runs])
    return states.min(axis=0), states.max(axis=0)


def within_mask(run: Trajectory, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(n,) bool: the samples of ``run`` whose every state lies in [low, high]."""
    return np.all((run.states >= low) & (run.states <= high), axis=1)


def within_stretches(runs: Sequence[Trajectory], low: np.ndarray, high: np.ndarray) -> list[Trajectory]:
    """The maximal stretches of ``runs`` whose every sample lies in [low, high] (so that no
    prediction window starts or ends outside), named ``<run>[first:end]``; the inputs go with
    their samples."""
    stretches = []
    for run in runs:
        inside = np.concatenate(([False], within_mask(run, low, high), [False]))
        edges = np.flatnonzero(np.diff(inside.astype(np.int8)))
        for first, end in zip(edges[::2], edges[1::2]):
            stretches.append(Trajectory(f"{run.name}[{first}:{end}]", run.states[first:end],
                                        run.inputs[first:end], run.state_names, run.input_names))
    return stretches


def outside_entries(runs: Sequence[Trajectory], low: np.ndarray, high: np.ndarray) -> list[dict[str, Any]]:
    """[{run, state, samples, of, low, high}] for each run and state with samples beyond
    [low, high]: their count, the run's length and the run's extremes of that state."""
    entries = []
    for run in runs:
        for j, name in enumerate(run.state_names):
            values = run.states[:, j]
            beyond = int(np.count_nonzero((values < low[j]) | (values > high[j])))
            if beyond:
                entries.append({"run": run.name, "state": name, "samples": beyond, "of": len(run),
                                "low": float(values.min()), "high": float(values.max())})
    return entries


def range_split(train_runs: Sequence[Trajectory],
                test_runs: Sequence[Trajectory]) -> tuple[dict[str, Any], list[Trajectory]]:
    """The test runs against the training runs' state range, without a model.

    Returns ({"training_min" / "training_max": {state: value}, "test_samples",
    "within_samples" (test samples with every state in the range), "outside":
    ``outside_entries`` of the test runs}, the test runs' ``within_stretches``).
    """
    names = train_runs[0].state_names
    low, high = state_range(train_runs)
    stretches = within_stretches(test_runs, low, high)
    return {
        "training_min": {name: float(v) for name, v in zip(names, low)},
        "training_max": {name: float(v) for name, v in zip(names, high)},
        "test_samples": int(sum(len(run) for run in test_runs)),
        "within_samples": int(sum(len(s) for s in stretches)),
        "outside": outside_entries(test_runs, low, high),
    }, stretches


def held_out_coverage(model: Predictor, train_runs: Sequence[Trajectory], test_runs: Sequence[Trajectory],
                      open_loop_steps: int = OPEN_LOOP_STEPS) -> dict[str, Any]:
    """:func:`range_split`'s figures plus "within_errors": ``prediction_errors`` of ``model``
    on the stretches within the range (None when no stretch is longer than
    ``open_loop_steps``)."""
    coverage, stretches = range_split(train_runs, test_runs)
    long_enough = [s for s in stretches if len(s) > open_loop_steps]
    coverage["within_errors"] = (prediction_errors(model, long_enough, open_loop_steps=open_loop_steps)
                                 if long_enough else None)
    return coverage


def coverage_lines(coverage: dict[str, Any]) -> list[str]:
    """One line per test run and state beyond the training range, then the test figures on
    the stretches within it; no lines when every test sample lies within."""
    if not coverage["outside"]:
        return []
    lines = []
    for entry in coverage["outside"]:
        state = entry["state"]
        lines.append(f"test run {entry['run']}: {entry['samples']} of {entry['of']} samples have {state} outside "
                     f"the training data's {coverage['training_min'][state]:.4g} .. "
                     f"{coverage['training_max'][state]:.4g} (the run's {entry['low']:.4g} .. {entry['high']:.4g}): "
                     "the test figures include extrapolation")
    within = coverage["within_errors"]
    if within is None:
        lines.append("no test stretch within the training range is long enough for the open-loop figures")
    else:
        share = coverage["within_samples"] / coverage["test_samples"]
        lines.append(f"within the training range ({100 * share:.0f} % of the test samples): "
                     + ", ".join(f"{name} one-step rmse {f['one_step_rmse']:.4f}, open-loop rmse {f['open_loop_rmse']:.4f}"
                                 for name, f in within.items()))
    return lines

"""Trajectories for system identification and the prediction-error figures of Table I.

numpy only. A predictor is anything with ``predict(x0 (batch, n_x), inputs (batch, n_steps,
n_u)) -> (batch, n_steps, n_x)``: the deep Koopman model and the DMDc / EDMDc baselines.

Convention: ``inputs[k]`` is the command applied over [t_k, t_k+1), so x_{k+1} = f(x_k, u_k).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

from models.koopman import KoopmanError

#: Open-loop horizon of the multi-step figure: 40 steps = 1 s at Ts = 0.025 s.
OPEN_LOOP_STEPS = 40


class Predictor(Protocol):
    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Trajectory:
    """One recorded run: ``states`` (n, n_x), ``inputs`` (n, n_u), equally spaced in time."""

    name: str
    states: np.ndarray
    inputs: np.ndarray
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]

    def __post_init__(self) -> None:
        states = np.asarray(self.states, dtype=float)
        inputs = np.asarray(self.inputs, dtype=float)
        if states.ndim != 2 or states.shape[1] != len(self.state_names):
            raise KoopmanError(f"run {self.name}: states must be (n, {len(self.state_names)}), got {states.shape}")
        if inputs.ndim != 2 or inputs.shape != (states.shape[0], len(self.input_names)):
            raise KoopmanError(
                f"run {self.name}: inputs must be ({states.shape[0]}, {len(self.input_names)}), got {inputs.shape}"
            )
        for values, names in ((states, self.state_names), (inputs, self.input_names)):
            bad = ~np.isfinite(values)
            if bad.any():
                row, col = np.argwhere(bad)[0]
                raise KoopmanError(
                    f"run {self.name}: non-finite value in column {names[col]!r} at row {row} "
                    f"({int(bad.any(axis=1).sum())} bad rows)"
                )
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "inputs", inputs)

    def __len__(self) -> int:
        return self.states.shape[0]


def open_loop_windows(
    runs: Sequence[Trajectory], n_steps: int, stride: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every start k (every ``stride``-th) with n_steps of future in the same run.

    Returns x0 (N, n_x), inputs (N, n_steps, n_u) = u_k..u_{k+n_steps-1},
    truth (N, n_steps, n_x) = x_{k+1}..x_{k+n_steps}. Windows never cross runs.
    """
    x0, inputs, truth = [], [], []
    for run in runs:
        n_starts = len(run) - n_steps
        if n_starts <= 0:
            continue
        starts = np.arange(0, n_starts, stride)
        offsets = np.arange(n_steps)
        x0.append(run.states[starts])
        inputs.append(run.inputs[starts[:, None] + offsets])
        truth.append(run.states[starts[:, None] + offsets + 1])
    if not x0:
        raise KoopmanError(f"no run is longer than {n_steps} steps; cannot evaluate {n_steps}-step predictions")
    return np.concatenate(x0), np.concatenate(inputs), np.concatenate(truth)


def prediction_errors(
    predictor: Predictor,
    runs: Sequence[Trajectory],
    open_loop_steps: int = OPEN_LOOP_STEPS,
    open_loop_stride: int = 5,
) -> dict[str, dict[str, float]]:
    """Table I figures per state on ``runs``.

    ``one_step_max`` / ``one_step_avg`` / ``one_step_rmse``: |x_{k+1} - x_hat_{k+1|k}| over
    every sample; ``open_loop_rmse``: RMSE over all predicted steps 1..open_loop_steps of
    open-loop rollouts (true inputs) started every ``open_loop_stride`` samples;
    ``open_loop_final_rmse``: the same at step ``open_loop_steps`` only.
    Returns {state_name: {figure: value}} in the state's unit.
    """
    names = runs[0].state_names
    x0, u1, truth1 = open_loop_windows(runs, 1)
    err1 = np.abs(predictor.predict(x0, u1)[:, 0] - truth1[:, 0])
    x0, u_h, truth_h = open_loop_windows(runs, open_loop_steps, open_loop_stride)
    err_h = predictor.predict(x0, u_h) - truth_h
    result: dict[str, dict[str, float]] = {}
    for j, name in enumerate(names):
        result[name] = {
            "one_step_max": float(err1[:, j].max()),
            "one_step_avg": float(err1[:, j].mean()),
            "one_step_rmse": float(np.sqrt(np.mean(err1[:, j] ** 2))),
            "open_loop_rmse": float(np.sqrt(np.mean(err_h[:, :, j] ** 2))),
            "open_loop_final_rmse": float(np.sqrt(np.mean(err_h[:, -1, j] ** 2))),
        }
    return result

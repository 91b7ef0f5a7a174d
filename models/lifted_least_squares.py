"""Least-squares lifted models (EDMDc) in the artefact format of the deep Koopman model.

The lift is fixed: z = [x; psi(x)], with psi the physics dictionary of
``models.koopman_dictionary`` (vy/vx, r/vx, vx r, vx^2/100 for data whose first states are
vx, vy, yaw rate; none otherwise, which is DMDc). The model is fitted in closed form, in
seconds, on the training runs' one-step pairs in normalised units (the min-max bounds of
``models.koopman_data``, as the network trains):

- ``edmdc-linear``:   z+ = A z + B u + c
- ``edmdc-bilinear``: z+ = A z + B u + sum_j u_j N_j z + c (bilinear in the input, as the
  ECU's bilinear form runs it)

by ridge-regularised least squares. The result is a ``NormalisedKoopman`` with no learned
features (an empty encoder), saved as ``<out>.npz`` / ``<out>.json``: both ECUs, the studies
and ``KoopmanModel.load`` take it as they take a trained model. Split by run, test errors
and the JSON's fields are those of ``models.koopman_train``; torch is not needed.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.koopman import KoopmanError, KoopmanModel
from models.koopman_artifact import NormalisedKoopman
from models.koopman_data import dictionary_scaling_of, fit_scaling, split_runs
from models.koopman_dictionary import DICTIONARY_STATES, check_dictionary, dictionary_features
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors
from models.koopman_settings import TrainingSettings

#: The closed-form forms: name -> bilinear in the input.
LEAST_SQUARES_FORMS = {"edmdc-linear": False, "edmdc-bilinear": True}
#: The default dictionary for data whose first states are DICTIONARY_STATES.
PHYSICS_DICTIONARY = ("vy/vx", "r/vx", "vx*r", "vx^2/100")
#: Ridge weight, relative to the mean diagonal of the normal equations.
DEFAULT_RIDGE = 1e-8


@dataclass(frozen=True)
class LeastSquaresResult:
    """The fitted model (physical units, metadata filled), what the ``.npz`` stores, the split."""

    model: KoopmanModel
    learned: NormalisedKoopman
    train_runs: list[str]
    val_runs: list[str]
    test_runs: list[str]
    seconds: float


def default_dictionary(state_names: Sequence[str]) -> tuple[str, ...]:
    """The physics dictionary where the states start with vx, vy, yaw rate; else none."""
    return PHYSICS_DICTIONARY if tuple(state_names[:3]) == DICTIONARY_STATES else ()


def _lifted(run: Trajectory, learned: NormalisedKoopman) -> tuple[np.ndarray, np.ndarray]:
    """Normalised lifted states z_n (T, n_z) and inputs u_n (T, n_u) of one run."""
    parts = [learned.state_scaling.normalise(run.states)]
    if learned.dictionary:
        parts.append(learned.dictionary_scaling.normalise(dictionary_features(learned.dictionary, run.states)))
    return np.hstack(parts), learned.input_scaling.normalise(run.inputs)


def _regressors(z: np.ndarray, u: np.ndarray, bilinear: bool) -> np.ndarray:
    """[z, u, 1, u_1 z, ..., u_m z] per row: (T, n_z + n_u + 1 (+ n_u n_z))."""
    columns = [z, u, np.ones((z.shape[0], 1))]
    if bilinear:
        columns += [u[:, j:j + 1] * z for j in range(u.shape[1])]
    return np.hstack(columns)


def fit_least_squares(runs: Sequence[Trajectory], ts: float, form: str, settings: TrainingSettings,
                      dictionary: Sequence[str] | None = None, ridge: float = DEFAULT_RIDGE,
                      metadata: dict[str, Any] | None = None) -> LeastSquaresResult:
    """Fit ``form`` (a key of ``LEAST_SQUARES_FORMS``) on the training runs of ``runs``.

    ``settings`` gives the split (seed, fractions, named runs); ``dictionary`` None takes
    ``default_dictionary``.

    Raises:
        KoopmanError: an unknown form, a bad dictionary, a split that cannot be made, or
            training pairs that do not determine the model (fewer pairs than regressors).
    """
    if form not in LEAST_SQUARES_FORMS:
        raise KoopmanError(f"least-squares form {form!r} is not one of {sorted(LEAST_SQUARES_FORMS)}")
    started = time.perf_counter()
    state_names, input_names = runs[0].state_names, runs[0].input_names
    names = check_dictionary(default_dictionary(state_names) if dictionary is None else tuple(dictionary),
                             state_names)
    train_runs, val_runs, test_runs = split_runs(runs, settings)
    state_scaling, input_scaling = fit_scaling(train_runs)
    shell = NormalisedKoopman(encoder=(), A_n=np.zeros((0, 0)), B_n=np.zeros((0, 0)), state_scaling=state_scaling,
                              input_scaling=input_scaling, dictionary=names,
                              dictionary_scaling=dictionary_scaling_of(train_runs, names))
    bilinear = LEAST_SQUARES_FORMS[form]
    rows, targets = [], []
    for run in train_runs:
        z, u = _lifted(run, shell)
        rows.append(_regressors(z[:-1], u[:-1], bilinear))
        targets.append(z[1:])
    regressors, target = np.vstack(rows), np.vstack(targets)
    n_z, n_u = target.shape[1], input_scaling.low.size
    if regressors.shape[0] < regressors.shape[1]:
        raise KoopmanError(f"{regressors.shape[0]} training pairs cannot fit {regressors.shape[1]} regressors")
    gram = regressors.T @ regressors
    gram += ridge * np.trace(gram) / gram.shape[0] * np.eye(gram.shape[0])
    theta = np.linalg.solve(gram, regressors.T @ target).T  # (n_z, regressors)
    A_n, B_n, affine_n = theta[:, :n_z], theta[:, n_z:n_z + n_u], theta[:, n_z + n_u]
    N_n = None
    if bilinear:
        N_n = np.stack([theta[:, n_z + n_u + 1 + j * n_z: n_z + n_u + 1 + (j + 1) * n_z] for j in range(n_u)])
    learned = NormalisedKoopman(encoder=(), A_n=A_n, B_n=B_n, state_scaling=state_scaling,
                                input_scaling=input_scaling, N_n=N_n, dictionary=names,
                                dictionary_scaling=shell.dictionary_scaling, affine_n=affine_n)
    meta = dict(metadata or {})
    meta.update(d=0, ts=float(ts), state_names=list(state_names), input_names=list(input_names),
                seed=settings.seed, fit="least squares, closed form (models/lifted_least_squares.py)",
                settings={"form": form, "dictionary": list(names), "ridge": ridge,
                          "val_runs": list(settings.val_runs), "test_runs": list(settings.test_runs),
                          "val_fraction": settings.val_fraction, "test_fraction": settings.test_fraction},
                split={"train": [r.name for r in train_runs], "validation": [r.name for r in val_runs],
                       "test": [r.name for r in test_runs]})
    model = KoopmanModel.from_normalised(learned, ts, state_names, input_names, meta)
    meta["spectral_radius_A"] = model.spectral_radius()
    meta["validation_errors"] = prediction_errors(model, val_runs, open_loop_steps=OPEN_LOOP_STEPS)
    meta["test_errors"] = prediction_errors(model, test_runs, open_loop_steps=OPEN_LOOP_STEPS)
    meta["test_open_loop_steps"] = OPEN_LOOP_STEPS
    elapsed = time.perf_counter() - started
    meta["training_seconds"] = round(elapsed, 3)
    model.metadata = meta
    return LeastSquaresResult(model=model, learned=learned, train_runs=[r.name for r in train_runs],
                              val_runs=[r.name for r in val_runs], test_runs=[r.name for r in test_runs],
                              seconds=elapsed)

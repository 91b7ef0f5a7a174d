"""The rows of a ``prediction`` grid (Table I, ``make table1``): a model form and how it is
made, its predictor for one seed, and the open-loop figures of a predictor on test runs.

A :class:`Row` is made one of these ways (``fit``, :data:`FITS`):

- ``train``: ``models.koopman_train.train`` with ``TrainingSettings(**overrides, seed)`` on
  the data's runs cut to the row's states; the artefact is cached in the campaign's folder
  (``prediction_training``: keyed by data hash, settings and states; the committed default
  artefact is taken where it matches);
- ``edmdc-linear`` / ``edmdc-bilinear``: the trainer's closed-form lifts
  (``models.lifted_least_squares.fit_least_squares``, as ``python -m models.koopman_train
  --form edmdc-linear --seed SEED`` fits them) on the data's runs with the trainer's default
  states;
- ``dmdc``, ``edmdc``: least squares on the seed's training runs (vx, vy, yaw rate);
- ``bicycle``, ``single_track``: LMPC's and NMPC's physics models, nominal parameters.

Every predictor sees the data's states (vx, vy, yaw rate, measured wheel angle) and predicts
vx, vy and yaw rate (:class:`VehicleStates`); :func:`evaluate` gives its one-step RMSE and the
open-loop RMSE over :data:`HORIZONS` on the seed's held-out test runs.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from models.koopman import KoopmanError
from models.koopman_baselines import DMDc, EDMDc
from models.koopman_metrics import Predictor, Trajectory, open_loop_windows
from models.koopman_settings import TrainingSettings
from models.lifted_least_squares import LEAST_SQUARES_FORMS, fit_least_squares
from studies.model_fidelity import BicyclePredictor, SingleTrackPredictor

TS = 0.025
VEHICLE_STATES = ("vx", "vy", "yaw_rate")
WHEEL_STATES = (*VEHICLE_STATES, "steer_measured")
HORIZONS = {"1 s": 40, "2 s": 80}
#: How a row's model is made (module docstring); the least-squares lifts by their ``--form``.
TRAIN_FIT = "train"
FITS = (TRAIN_FIT, *LEAST_SQUARES_FORMS, "dmdc", "edmdc", "bicycle", "single_track")
#: The note of each row without training or fit of a lift (the report's list under the table).
FIXED_NOTES = {
    "dmdc": "x+ = A x + B u + c, least squares",
    "edmdc": "fixed dictionary of degree 2-3 monomials, least squares (ridge 1e-6)",
    "bicycle": "nominal parameters, speed held at its start value",
    "single_track": "nominal parameters, Magic Formula tyres, RK4 at Ts",
}


@dataclass(frozen=True)
class Row:
    """A row of the table: its label, how its model is made (``fit``, :data:`FITS`), the
    ``TrainingSettings`` overrides (``train`` and the least-squares lifts) and the states
    its model sees (``train``: the data's runs are cut to them)."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)
    states: tuple[str, ...] = WHEEL_STATES
    fit: str = TRAIN_FIT


@dataclass(frozen=True)
class Fitted:
    """A row's predictor for one seed: on the data's states -> (batch, n, 3); the largest
    spectral radius of its lifted A (None: a physics model), its note, and ``best/run``
    epochs (None: no training)."""

    predictor: Predictor
    rho: float | None
    note: str
    epochs: str | None = None


class VehicleStates:
    """Adapts a predictor to the data's states: it sees its own leading states, returns vx, vy, r."""

    def __init__(self, predictor: Predictor, n_states: int) -> None:
        self.predictor, self.n_states = predictor, n_states

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, >= n_states), inputs (batch, n, 2) -> (batch, n, 3)."""
        return self.predictor.predict(x0[:, : self.n_states], inputs)[..., :3]


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


def one_step_trace(predictor: Predictor, run: Trajectory) -> np.ndarray:
    """One-step prediction errors of vx, vy, yaw rate along ``run`` (len(run) - 1, 3)."""
    return predictor.predict(run.states[:-1], run.inputs[:-1, None, :])[:, 0] - run.states[1:, :3]


def settings_of(row: Row, seed: int) -> TrainingSettings:
    """The row's ``TrainingSettings`` for ``seed``: its overrides, the seed."""
    return TrainingSettings(**{**row.overrides, "seed": seed})


def fit_closed_form(row: Row, seed: int, runs: Sequence[Trajectory], train_runs: Sequence[Trajectory],
                    test_runs: Sequence[Trajectory]) -> Fitted:
    """The predictor of a row without training (``fit`` not ``train``) for ``seed``: ``runs``
    are the data's runs (:data:`WHEEL_STATES`), ``train_runs`` / ``test_runs`` their split.

    Raises:
        KoopmanError: a least-squares lift whose test runs differ from the split's.
    """
    if row.fit in LEAST_SQUARES_FORMS:
        model = fit_least_squares(runs, TS, row.fit, settings_of(row, seed)).model
        if model.metadata["split"]["test"] != [r.name for r in test_runs]:
            raise KoopmanError(f"{row.label} seed {seed}: the fit's test runs differ from the table's split")
        return Fitted(VehicleStates(model, len(model.state_names)), model.spectral_radius(),
                      f"{row.fit} of the trainer, closed form, states {', '.join(model.state_names)}, "
                      f"dictionary {', '.join(model.dictionary)}, n_z = {model.n_z}")
    if row.fit in ("dmdc", "edmdc"):
        vehicle = [Trajectory(r.name, r.states[:, :3], r.inputs, VEHICLE_STATES, r.input_names) for r in train_runs]
        model = DMDc().fit(vehicle) if row.fit == "dmdc" else EDMDc(degree=3).fit(vehicle)
        return Fitted(VehicleStates(model, 3), model.spectral_radius(), FIXED_NOTES[row.fit])
    if row.fit == "bicycle":
        return Fitted(VehicleStates(BicyclePredictor(), 3), None, FIXED_NOTES["bicycle"])
    if row.fit == "single_track":
        return Fitted(VehicleStates(SingleTrackPredictor(), 3), None, FIXED_NOTES["single_track"])
    raise KoopmanError(f"{row.label}: fit {row.fit!r} is not a closed form; known: {', '.join(FITS)}")


def fitted_model(row: Row, seed: int, model: Any, test_runs: Sequence[Trajectory]) -> Fitted:
    """A trained row's loaded artefact ``model`` (a ``KoopmanModel``) as its predictor.

    Raises:
        KoopmanError: the model's test runs differ from the split's.
    """
    if model.metadata["split"]["test"] != [r.name for r in test_runs]:
        raise KoopmanError(f"{row.label} seed {seed}: the model's test runs differ from the split; "
                           "delete its cached model")
    return Fitted(VehicleStates(model, len(row.states)), model.spectral_radius(),
                  f"{model.form} form, states {', '.join(row.states)}, n_z = {model.n_z}",
                  f"{model.metadata['best_epoch']}/{model.metadata['epochs_run']}")

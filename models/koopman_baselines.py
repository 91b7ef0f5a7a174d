"""Baselines for Table I, fitted by linear least squares on the same runs (numpy only).

- ``DMDc``: x_{k+1} = A x_k + B u_k + c on the physical state (dynamic mode decomposition
  with control, plus an affine term).
- ``EDMDc``: the same on a FIXED dictionary psi(x) = [x; all monomials of degree 2..degree
  of the min-max normalised state], z_{k+1} = A z_k + B u_k + c, x = C_P z with C_P = [I, 0].

Both follow the estimator habit: hyper-parameters in the constructor, ``fit(runs)`` returns
self, learned attributes end in ``_``, and ``predict(x0 (batch, n_x), inputs (batch, n_steps,
n_u)) -> (batch, n_steps, n_x)`` as the deep Koopman model.
"""
from __future__ import annotations

from itertools import combinations_with_replacement
from typing import Sequence

import numpy as np

from models.koopman import KoopmanError, KoopmanModel, MinMaxScaling
from models.koopman_metrics import Trajectory


def _pairs(runs: Sequence[Trajectory]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Snapshot pairs within runs: x_k (N, n_x), u_k (N, n_u), x_{k+1} (N, n_x)."""
    usable = [r for r in runs if len(r) >= 2]
    if not usable:
        raise KoopmanError("no run has two samples; nothing to fit")
    return (
        np.concatenate([r.states[:-1] for r in usable]),
        np.concatenate([r.inputs[:-1] for r in usable]),
        np.concatenate([r.states[1:] for r in usable]),
    )


def _affine_least_squares(
    lifted: np.ndarray, inputs: np.ndarray, lifted_next: np.ndarray, ridge: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve lifted_next ~ A lifted + B inputs + c (ridge-regularised, columns standardised).

    lifted (N, n_z), inputs (N, n_u), lifted_next (N, n_z) -> A (n_z, n_z), B (n_z, n_u), c (n_z,).
    """
    regressors = np.hstack([lifted, inputs])
    mean = regressors.mean(axis=0)
    std = regressors.std(axis=0)
    std = np.where(std > 1e-12, std, 1.0)
    scaled = (regressors - mean) / std
    target_mean = lifted_next.mean(axis=0)
    gram = scaled.T @ scaled + ridge * len(scaled) * np.eye(scaled.shape[1])
    coef = np.linalg.solve(gram, scaled.T @ (lifted_next - target_mean))  # (n_reg, n_z)
    coef = coef / std[:, None]
    n_z = lifted.shape[1]
    A = coef[:n_z].T
    B = coef[n_z:].T
    c = target_mean - mean @ coef
    return A, B, c


class _LiftedLinear:
    """Shared rollout of z+ = A z + B u + c from a lifting ``_lift``."""

    A_: np.ndarray
    B_: np.ndarray
    offset_: np.ndarray
    n_x_: int

    def _lift(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, n_x), inputs (batch, n_steps, n_u) -> (batch, n_steps, n_x)."""
        if not hasattr(self, "A_"):
            raise KoopmanError(f"{type(self).__name__} is not fitted; call fit(runs) first")
        z = self._lift(np.asarray(x0, dtype=float))
        forced = np.asarray(inputs, dtype=float) @ self.B_.T + self.offset_
        out = np.empty(inputs.shape[:2] + (self.n_x_,))
        for i in range(inputs.shape[1]):
            z = z @ self.A_.T + forced[:, i]
            out[:, i] = z[:, : self.n_x_]
        return out

    def spectral_radius(self) -> float:
        return float(np.max(np.abs(np.linalg.eigvals(self.A_))))


class DMDc(_LiftedLinear):
    """Linear least squares on the state with an affine term: x+ = A x + B u + c."""

    def __init__(self, ridge: float = 1e-8) -> None:
        self.ridge = ridge

    def _lift(self, x: np.ndarray) -> np.ndarray:
        return x

    def fit(self, runs: Sequence[Trajectory]) -> "DMDc":
        x, u, x_next = _pairs(runs)
        self.n_x_ = x.shape[1]
        self.A_, self.B_, self.offset_ = _affine_least_squares(x, u, x_next, self.ridge)
        self.state_names_ = runs[0].state_names
        self.input_names_ = runs[0].input_names
        return self

    def to_koopman_model(self, ts: float) -> KoopmanModel:
        """The fitted DMDc as a ``KoopmanModel`` with no learned features (z = x)."""
        return KoopmanModel(self.A_, self.B_, self.offset_, [], ts, self.state_names_, self.input_names_,
                            {"kind": "DMDc"})


class EDMDc(_LiftedLinear):
    """Least squares on a fixed polynomial dictionary of the min-max normalised state."""

    def __init__(self, degree: int = 3, ridge: float = 1e-6) -> None:
        if degree < 2:
            raise KoopmanError(f"EDMDc degree must be >= 2 (degree 1 is DMDc), got {degree}")
        self.degree = degree
        self.ridge = ridge

    def _lift(self, x: np.ndarray) -> np.ndarray:
        """x (batch, n_x) -> psi(x) (batch, n_z) = [x; monomials of x_n of degree 2..degree]."""
        x_n = self.scaling_.normalise(x)
        terms = [x] + [np.prod(x_n[:, list(idx)], axis=1, keepdims=True) for idx in self.monomials_]
        return np.hstack(terms)

    def fit(self, runs: Sequence[Trajectory]) -> "EDMDc":
        x, u, x_next = _pairs(runs)
        self.n_x_ = x.shape[1]
        self.scaling_ = MinMaxScaling(x.min(axis=0), np.maximum(x.max(axis=0), x.min(axis=0) + 1e-9))
        self.monomials_ = [
            idx for deg in range(2, self.degree + 1)
            for idx in combinations_with_replacement(range(self.n_x_), deg)
        ]
        self.A_, self.B_, self.offset_ = _affine_least_squares(self._lift(x), u, self._lift(x_next), self.ridge)
        return self

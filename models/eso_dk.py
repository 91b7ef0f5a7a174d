"""ESO-DK predictor: the deep Koopman model plus the ESO's disturbance estimate (eq. 15).

    z[k|k]       = lift(x[k])                          measured state, lifted (eq. 6)
    z[k+i+1|k]   = A z[k+i|k] + B u[k+i] + offset + w_hat    w_hat held over the horizon
    x[k+i|k]     = C_P z[k+i|k]                        (eq. 7)

DK is the same recursion with w_hat = 0, so the two predictors differ only in the estimate.

Timing within a cycle k: ``observe(x[k], u[k])`` runs eq. 13 with z[k] = lift(x[k]); the
estimate it leaves, w_hat[k+1] = w_hat[k] - beta2 g2(z[k] - z_hat[k]), already contains
z[k] and does not depend on u[k] (``models.eso.innovated_disturbance`` gives it before
u[k] is chosen, for an MPC). Predictions from x[k] then use that estimate.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from models.eso import (CorrectionFunction, EsoParams, EsoShapeError, ExtendedStateObserver,
                        identity_correction)


class LiftedLinearModel(Protocol):
    """What the predictor needs of ``models.koopman.KoopmanModel``."""

    A: np.ndarray  # (n_z, n_z)
    B: np.ndarray  # (n_z, n_u)
    offset: np.ndarray  # (n_z,)
    C_P: np.ndarray  # (n_x, n_z)
    n_x: int
    n_u: int
    n_z: int

    def lift(self, x: np.ndarray) -> np.ndarray:  # (..., n_x) -> (..., n_z)
        ...


def observer_params(model: LiftedLinearModel, beta1: np.ndarray | float, beta2: np.ndarray | float,
                    g2: CorrectionFunction = identity_correction) -> EsoParams:
    """The ESO of eq. 13 on ``model`` (A, B, offset and, for a bilinear model, N) with these
    gains and correction g2 (the identity by default, as the paper)."""
    bilinear = getattr(model, "N", None) if getattr(model, "form", "linear") == "bilinear" else None
    return EsoParams(model.A, model.B, model.offset, beta1, beta2, g2=g2, bilinear=bilinear)


def rollout_lifted(
    model: LiftedLinearModel,
    z0: np.ndarray,
    inputs: np.ndarray,
    disturbance: np.ndarray | None = None,
) -> np.ndarray:
    """Lifted rollout with a held disturbance, vectorised over a batch.

    z0 (batch, n_z), inputs (batch, n_steps, n_u), disturbance (batch, n_z) or (n_z,) or
    None (= 0, plain DK) -> lifted predictions (batch, n_steps, n_z), entry [:, i] being
    z[k+i+1|k].
    """
    z = np.asarray(z0, dtype=float)
    inputs = np.asarray(inputs, dtype=float)
    if z.ndim != 2 or z.shape[1] != model.n_z:
        raise EsoShapeError(f"z0 must be (batch, {model.n_z}), got {z.shape}")
    if inputs.ndim != 3 or inputs.shape[0] != z.shape[0] or inputs.shape[2] != model.n_u:
        raise EsoShapeError(f"inputs must be ({z.shape[0]}, n_steps, {model.n_u}), got {inputs.shape}")
    # Input, offset and held disturbance enter every step identically: add them up front;
    # a bilinear model's state-dependent input term is added per step (with the predicted z).
    bilinear = getattr(model, "N", None) if getattr(model, "form", "linear") == "bilinear" else None
    forced = inputs @ model.B.T + model.offset
    if disturbance is not None:
        held = np.asarray(disturbance, dtype=float)
        if held.shape not in ((model.n_z,), (z.shape[0], model.n_z)):
            raise EsoShapeError(f"disturbance must be ({model.n_z},) or ({z.shape[0]}, {model.n_z}), got {held.shape}")
        forced = forced + (held[:, None, :] if held.ndim == 2 else held)
    out = np.empty(inputs.shape[:2] + (model.n_z,))
    a_t = model.A.T
    for i in range(inputs.shape[1]):
        z_next = z @ a_t + forced[:, i]
        if bilinear is not None:
            z_next += np.einsum("bj,jac,bc->ba", inputs[:, i], bilinear, z)
        z = z_next
        out[:, i] = z
    return out


class EsoDkPredictor:
    """Deep Koopman model corrected by the lifted-space ESO (ESO-DK).

    ``model``: a KoopmanModel (A, B, offset, C_P, lift); ``observer_params``: EsoParams
    whose A, B, offset are the model's (checked).
    """

    def __init__(self, model: LiftedLinearModel, observer_params: EsoParams) -> None:
        for name in ("A", "B", "offset"):
            if not np.array_equal(np.asarray(getattr(model, name)), getattr(observer_params, name)):
                raise EsoShapeError(f"observer_params.{name} differs from the model's {name}")
        self.model = model
        self.observer = ExtendedStateObserver(observer_params)

    def reset(self, x0: np.ndarray) -> None:
        """Restart the observer at the lifted measured state x0 (n_x,), w_hat = 0."""
        self.observer.reset(self.model.lift(np.asarray(x0, dtype=float)))

    def observe(self, x: np.ndarray, u: np.ndarray) -> bool:
        """ESO step with the measured state x[k] (n_x,) and the input u[k] (n_u,) applied.

        False (estimate untouched) for a non-finite measurement or input.
        """
        x = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(x)):
            return False
        return self.observer.update(self.model.lift(x), u)

    @property
    def disturbance_estimate(self) -> np.ndarray:
        """Current w_hat (n_z,)."""
        return self.observer.disturbance_estimate

    def predict(self, x: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Multi-step ESO-DK prediction from the measured x[k] (n_x,) with w_hat held.

        inputs (n_steps, n_u) = u[k..k+n_steps-1] -> states (n_steps, n_x), row i = x[k+i+1|k].
        """
        z0 = self.model.lift(np.asarray(x, dtype=float))[None, :]
        lifted = rollout_lifted(self.model, z0, np.asarray(inputs, dtype=float)[None], self.disturbance_estimate)
        return lifted[0] @ self.model.C_P.T

    def predict_one_step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x[k+1|k] (n_x,) from x[k] (n_x,) and u[k] (n_u,) (eq. 15 with N_p = 1)."""
        z = self.model.lift(np.asarray(x, dtype=float))
        z_next = rollout_lifted(self.model, z[None], np.asarray(u, dtype=float)[None, None])[0, 0]
        return self.model.C_P @ (z_next + self.disturbance_estimate)

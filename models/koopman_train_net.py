"""The deep Koopman network in torch (build time only; the ECU never imports this).

Network (Fig. 2, Remark 4): encoder Phi = MLP of tanh layers giving d learned features; the
lifted state z = [x; psi(x); Phi(x)] (eq. 6 plus the fixed dictionary psi of
``models.koopman.DICTIONARY``), x = C_P z (eq. 7); a decoder Phi^-1 (mirror of the encoder)
for the reconstruction loss. Everything is in min-max normalised units.

Dynamics (``form``):
- ``linear``, the paper's eq. 5: z+ = A z + B u, A and B bias-free linear maps;
- ``bilinear``: z+ = A z + B u + c + sum_j u_j N_j z, the input matrix depends on the lifted
  state (why: ``models/koopman.py``), with a learned constant c;
- ``scheduled``: z+ = A(v) z + B(v) u + c(v), one (A, B, c) per speed knot, interpolated
  at the speed v of the sequence's first sample and held over the sequence (as the MPC).
  ``shared_rows`` (state indices) keep one row of (A, B, c) for all knots: the mean of the
  knots' rows is used everywhere, so those states' dynamics do not depend on speed.

Loss per sequence x_k..x_{k+p-1}, u_k..u_{k+p-2} (means over their terms):
- L1, multi-step prediction (eqs. 9-10), rolled out in the LIFTED space from z_k, as the MPC
  does. The error of each state is weighted to physical units over that state's standard
  deviation in the training runs, so vx (tens of m/s) does not drown vy and r.
- L2, reconstruction (eq. 11): x_k vs Phi^-1(Phi(x_k)).
- L3, lifted consistency (our addition): the true future [psi; Phi] vs the rolled-out ones,
  which keeps the lifted coordinates predictable over the horizon.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn

from models.koopman import MinMaxScaling, NormalisedKoopman


class KoopmanNet(nn.Module):
    """Encoder, decoder and the dynamics A, B (and N, c for the bilinear form), normalised units."""

    def __init__(self, n_x: int, n_u: int, n_features: int, hidden: Sequence[int],
                 n_dictionary: int = 0, bilinear: bool = False, n_knots: int = 0,
                 shared_rows: Sequence[int] = ()) -> None:
        super().__init__()
        self.shared_rows = list(shared_rows)
        self.n_x, self.n_u, self.n_features = n_x, n_u, n_features
        self.n_known = n_x + n_dictionary
        self.n_z = self.n_known + n_features
        self.encoder = _mlp(n_x, hidden, n_features)
        self.decoder = _mlp(n_features, tuple(reversed(hidden)), n_x)
        self.A = nn.Linear(self.n_z, self.n_z, bias=False)
        self.B = nn.Linear(n_u, self.n_z, bias=False)
        self.N = nn.Parameter(torch.zeros(n_u, self.n_z, self.n_z)) if bilinear else None
        self.c = nn.Parameter(torch.zeros(self.n_z)) if bilinear else None
        self.n_knots = n_knots
        if n_knots:  # one (A, B, c) per speed knot
            self.A_knots = nn.Parameter(torch.eye(self.n_z).repeat(n_knots, 1, 1))
            self.B_knots = nn.Parameter(torch.zeros(n_knots, self.n_z, n_u))
            self.c_knots = nn.Parameter(torch.zeros(n_knots, self.n_z))
        with torch.no_grad():
            # Start near "nothing moves in 25 ms": a stable, well-conditioned first guess.
            self.A.weight.copy_(torch.eye(self.n_z) + 0.01 * self.A.weight)
            self.B.weight.mul_(0.1)

    @torch.no_grad()
    def warm_start(self, fit: dict[str, np.ndarray]) -> None:
        """Start the rows of the known coordinates [x; psi] from a least-squares fit.

        ``fit`` holds A (k, k), B (k, n_u) and, for the bilinear form, N (n_u, k, k) and
        c (k,), k = n_known, in normalised units. The learned features start with no
        influence on the known coordinates, so the first rollouts are those of the best
        (bi)linear model in x and psi; training only has to add what the features explain.
        """
        k = self.n_known
        dtype = self.A.weight.dtype
        if self.n_knots:
            self.A_knots[:, :k, :k] = torch.as_tensor(fit["A"], dtype=dtype)
            self.A_knots[:, :k, k:] = 0.0
            self.B_knots[:, :k] = torch.as_tensor(fit["B"], dtype=dtype)
            self.c_knots[:, :k] = torch.as_tensor(fit["c"], dtype=dtype)
            return
        self.A.weight[:k, :k] = torch.as_tensor(fit["A"], dtype=dtype)
        self.A.weight[:k, k:] = 0.0
        self.B.weight[:k] = torch.as_tensor(fit["B"], dtype=dtype)
        if self.N is not None:
            self.N[:, :k, :k] = torch.as_tensor(fit["N"], dtype=dtype)
            self.c[:k] = torch.as_tensor(fit["c"], dtype=dtype)

    def lift(self, x_n: torch.Tensor, psi_n: torch.Tensor) -> torch.Tensor:
        """x_n (..., n_x), psi_n (..., n_dict) -> z_n (..., n_z) = [x_n; psi_n; Phi(x_n)] (eq. 6)."""
        return torch.cat([x_n, psi_n, self.features(x_n)], dim=-1)

    def features(self, x_n: torch.Tensor) -> torch.Tensor:
        """The learned features Phi: x_n (..., n_x) -> (..., d)."""
        return self.encoder(x_n)

    def step(self, z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """One step of the dynamics: z (batch, n_z), u (batch, n_u) -> (batch, n_z)."""
        z_next = self.A(z) + self.B(u)
        if self.N is not None:
            z_next = z_next + self.c + torch.einsum("bj,jac,bc->ba", u, self.N, z)
        return z_next

    def rollout(self, z0: torch.Tensor, inputs_n: torch.Tensor,
                knot_weights: torch.Tensor | None = None) -> torch.Tensor:
        """z0 (batch, n_z), inputs_n (batch, n_steps, n_u) -> z_hat (batch, n_steps, n_z).

        ``knot_weights`` (batch, K): the scheduled form's interpolation weights, held.
        """
        z = z0
        out = []
        if self.n_knots:
            A_knots, B_knots, c_knots = self.knot_matrices()
            A = torch.einsum("bk,kij->bij", knot_weights, A_knots)
            forced = (torch.einsum("bk,kij,bsj->bsi", knot_weights, B_knots, inputs_n)
                      + (knot_weights @ c_knots)[:, None])
            for i in range(inputs_n.shape[1]):
                z = torch.einsum("bij,bj->bi", A, z) + forced[:, i]
                out.append(z)
            return torch.stack(out, dim=1)
        for i in range(inputs_n.shape[1]):
            z = self.step(z, inputs_n[:, i])
            out.append(z)
        return torch.stack(out, dim=1)

    def knot_matrices(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A (K, n_z, n_z), B (K, n_z, n_u), c (K, n_z) of the scheduled form, the rows of
        ``shared_rows`` replaced by their mean over the knots (not scheduled on speed)."""
        A, B, c = self.A_knots, self.B_knots, self.c_knots
        if not self.shared_rows:
            return A, B, c
        rows = self.shared_rows
        A, B, c = A.clone(), B.clone(), c.clone()
        A[:, rows] = self.A_knots[:, rows].mean(dim=0)
        B[:, rows] = self.B_knots[:, rows].mean(dim=0)
        c[:, rows] = self.c_knots[:, rows].mean(dim=0)
        return A, B, c

    def losses(self, x_n: torch.Tensor, psi_n: torch.Tensor, u_n: torch.Tensor,
               state_weights: torch.Tensor, knot_weights: torch.Tensor | None = None,
               step_knot_weights: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """x_n (batch, p, n_x), psi_n (batch, p, n_dict), u_n (batch, p - 1, n_u),
        state_weights (n_x,), knot_weights (batch, K) or None, step_knot_weights (batch,
        p - 1, K) or None (each step's own speed, for networks whose ``rollout`` takes them)
        -> the three loss terms (scalars) and the weighted errors (batch, p - 1, n_x)."""
        features = self.features(x_n)
        z0 = torch.cat([x_n[:, 0], psi_n[:, 0], features[:, 0]], dim=-1)
        z_hat = (self.rollout(z0, u_n, knot_weights) if step_knot_weights is None
                 else self.rollout(z0, u_n, knot_weights, step_knot_weights))
        error = (z_hat[..., : self.n_x] - x_n[:, 1:]) * state_weights
        prediction = torch.mean(error ** 2)  # eqs. 9-10
        # eq. 11 as printed reconstructs x_k, the first state of the sequence; the batch's
        # overlapping windows cover the same states, at a third of the decoder cost.
        reconstruction = torch.mean((self.decoder(features[:, 0]) - x_n[:, 0]) ** 2)
        future = torch.cat([psi_n[:, 1:], features[:, 1:]], dim=-1)
        lifted = torch.mean((z_hat[..., self.n_x:] - future) ** 2)  # our addition
        return {"prediction": prediction, "reconstruction": reconstruction, "lifted": lifted,
                "error": error}

    def export(self, state_scaling: MinMaxScaling, input_scaling: MinMaxScaling,
               dictionary: tuple[str, ...] = (),
               dictionary_scaling: MinMaxScaling | None = None,
               speed_knots: tuple[float, ...] = ()) -> NormalisedKoopman:
        """The learned weights as float64 numpy arrays (encoder, A_n, B_n, N_n, affine_n)."""
        def array(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().double().numpy().copy()

        layers = [m for m in self.encoder if isinstance(m, nn.Linear)]
        if self.n_knots:
            A_knots, B_knots, c_knots = self.knot_matrices()
            return NormalisedKoopman(
                encoder=tuple((array(layer.weight), array(layer.bias)) for layer in layers),
                A_n=array(A_knots), B_n=array(B_knots), state_scaling=state_scaling,
                input_scaling=input_scaling, dictionary=dictionary, dictionary_scaling=dictionary_scaling,
                affine_n=array(c_knots), speed_knots=tuple(float(v) for v in speed_knots))
        return NormalisedKoopman(
            encoder=tuple((array(layer.weight), array(layer.bias)) for layer in layers),
            A_n=array(self.A.weight),
            B_n=array(self.B.weight),
            state_scaling=state_scaling,
            input_scaling=input_scaling,
            N_n=None if self.N is None else array(self.N),
            dictionary=dictionary,
            dictionary_scaling=dictionary_scaling,
            affine_n=None if self.c is None else array(self.c),
        )


def _mlp(n_in: int, hidden: Sequence[int], n_out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    width = n_in
    for h in hidden:
        layers += [nn.Linear(width, h), nn.Tanh()]
        width = h
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


def _ridge_solve(X: np.ndarray, Y: np.ndarray, ridge: float) -> np.ndarray:
    """coef (n_reg, n_out) of Y (n, n_out) ~ X (n, n_reg) coef, the ridge scaled by the Gram
    matrix's mean diagonal so it means the same in any units."""
    gram = X.T @ X
    return np.linalg.solve(gram + ridge * np.trace(gram) / len(gram) * np.eye(len(gram)), X.T @ Y)


def least_squares_start(known: Sequence[np.ndarray], inputs: Sequence[np.ndarray],
                        bilinear: bool, ridge: float = 1e-6,
                        knot_weights: Sequence[np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """One-step least squares of the known coordinates, normalised units, for ``warm_start``.

    ``known``: per run (n, k) = [x_n, psi_n]; ``inputs``: per run (n, n_u). Linear form:
    k+ = A k + B u (bias-free, as eq. 5); bilinear: k+ = A k + B u + c + sum_j u_j N_j k.
    Returns {"A": (k, k), "B": (k, n_u)[, "N": (n_u, k, k), "c": (k,)]}. With
    ``knot_weights`` (per run (n, K)): the scheduled form k+ = sum_m w_m (A_m k + B_m u + c_m),
    returning A (K, k, k), B (K, k, n_u), c (K, k).
    """
    if knot_weights is not None:
        return _scheduled_least_squares(known, inputs, knot_weights, ridge)
    regressors, targets = [], []
    for z, u in zip(known, inputs):
        parts = [z[:-1], u[:-1]]
        if bilinear:
            parts.append(np.ones((len(z) - 1, 1)))
            parts.extend(u[:-1, j:j + 1] * z[:-1] for j in range(u.shape[1]))
        regressors.append(np.hstack(parts))
        targets.append(z[1:])
    coef = _ridge_solve(np.concatenate(regressors), np.concatenate(targets), ridge)
    k, n_u = targets[0].shape[1], inputs[0].shape[1]
    fit = {"A": coef[:k].T, "B": coef[k:k + n_u].T}
    if bilinear:
        fit["c"] = coef[k + n_u]
        rest = coef[k + n_u + 1:]
        fit["N"] = np.stack([rest[j * k:(j + 1) * k].T for j in range(n_u)])
    return fit


def _scheduled_least_squares(known: Sequence[np.ndarray], inputs: Sequence[np.ndarray],
                             knot_weights: Sequence[np.ndarray], ridge: float) -> dict[str, np.ndarray]:
    """Least squares of the scheduled form (see ``least_squares_start``)."""
    regressors, targets = [], []
    for z, u, w in zip(known, inputs, knot_weights):
        base = np.hstack([z[:-1], u[:-1], np.ones((len(z) - 1, 1))])  # (n, k + n_u + 1)
        regressors.append((w[:-1, :, None] * base[:, None, :]).reshape(len(base), -1))
        targets.append(z[1:])
    coef = _ridge_solve(np.concatenate(regressors), np.concatenate(targets), ridge)
    k, n_u, n_knots = targets[0].shape[1], inputs[0].shape[1], knot_weights[0].shape[1]
    per_knot = coef.reshape(n_knots, k + n_u + 1, k)
    return {"A": per_knot[:, :k].transpose(0, 2, 1), "B": per_knot[:, k:k + n_u].transpose(0, 2, 1),
            "c": per_knot[:, k + n_u]}

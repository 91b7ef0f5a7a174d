"""A left / right mirror-symmetric deep Koopman network (build time only; torch).

Why: a car that is symmetric left to right, driving straight with the wheels straight, does
not turn, and its response to a steer of -delta is the mirror of its response to +delta.
The free network of ``models/koopman_train_net.py`` learns that only approximately, and the
seed decides how well: its step-steer error over seeds is mostly a yaw rate the model
predicts with the steer held at 0 (docs/koopman.md, "Step steer over seeds"). This network
has the symmetry by construction.

The mirror P flips the sign of the lateral quantities (``PARITY``: vy, yaw rate, wheel
angle, steer command, and the odd dictionary terms) and keeps the longitudinal ones (vx,
torque). In the min-max normalised units of training, x_n = (x - lo) / (hi - lo), it is the
reflection about the normalised image of 0: P x_n = 2 x0_n - x_n on the odd channels, with
x0_n = -lo / (hi - lo).

- Features: the encoder g gives d values; the first ``even_features`` are made even,
  (g(x) + g(Px)) / 2, the others odd, (g(x) - g(Px)) / 2.
- Dynamics (the scheduled form, per speed knot; the speed is even, so scheduling on it keeps
  the symmetry): with the lifted state centred on the image of 0, z_c = z_n - z0_n, the
  model z_c+ = A z_c + B u_c + c_c is equivariant when A maps even coordinates to even ones
  and odd to odd, B maps the torque to even rows and the steer to odd rows, and c_c is 0 on
  the odd rows. In the normalised coordinates of the artefact that is the affine term
  c = c_c + z0_n - A z0_n - B u0_n, whose odd rows are fixed by A and B (``knot_matrices``).
- Optional ``servo_lag``: the wheel-angle row is a first-order lag of unit DC gain from the
  steer command, delta+ = a delta + (1 - a) u, one a in (0, 1) per knot; the state and the
  input then share their min-max bounds so that the unit gain holds in physical units too.
- Optional ``steer_bilinear``: a steer-bilinear term (u_s - u0_s) N(v) (z_n - z0_n), N per
  knot, so that the response to a steer change depends on the state at a given speed
  (docs/koopman.md, "What the data hold"): the linear-range gain near straight driving,
  a lower one near the limit. Equivariance needs N to map even coordinates to odd rows and
  odd ones to even rows (the steer is odd); the wheel-angle row keeps its lag. Still linear
  in the input at each step, so the MPC stays a QP with B(z_k) held over the horizon.
- Optional per-step schedule of the lateral (odd) rows in training: their (A, B, c) are
  those of each step's measured speed instead of the window's first speed, so each knot
  learns the lateral dynamics of its own speed rather than an average over a braking or
  accelerating window. The longitudinal rows keep the held speed (scheduling them per step
  would hand them the future speed they are to predict). At run time every row is held at
  the measured speed, as the MPC does.

The export is an ordinary scheduled artefact: the two encoder passes become one MLP of twice
the width with block-diagonal hidden layers (``export``), so ``models/koopman.py``, the ECU
and the C firmware load it unchanged. With ``steer_bilinear`` the centred term is folded
into the artefact's per-knot (A_n, B_n, affine_n, N_n) of the plain bilinear form.
"""
from __future__ import annotations

import copy
from typing import Sequence

import numpy as np
import torch
from torch import nn

from models.koopman import KoopmanError, MinMaxScaling, NormalisedKoopman
from models.koopman_train_net import KoopmanNet

#: Parity under the left / right mirror: +1 even (unchanged), -1 odd (sign flips).
PARITY = {
    "vx": 1, "vy": -1, "yaw_rate": -1, "steer_measured": -1,  # states
    "torque": 1, "steer": -1,  # inputs
    "vy/vx": -1, "r/vx": -1, "vx*r": -1, "vx^2/100": 1,  # dictionary terms
}
#: The wheel angle state and the command it follows (``servo_lag``).
SERVO_STATE, SERVO_INPUT = "steer_measured", "steer"


def parities(names: Sequence[str]) -> np.ndarray:
    """Mirror parity (+1 / -1) of each name, (len(names),); KoopmanError names an unknown one."""
    unknown = [name for name in names if name not in PARITY]
    if unknown:
        raise KoopmanError(f"mirror symmetry: no parity known for {unknown} (known: {sorted(PARITY)})")
    return np.array([PARITY[name] for name in names], dtype=float)


def shared_servo_scaling(state_scaling: MinMaxScaling, input_scaling: MinMaxScaling,
                         state_names: Sequence[str], input_names: Sequence[str]
                         ) -> tuple[MinMaxScaling, MinMaxScaling]:
    """The wheel angle's and the steer command's bounds replaced by their union, so that a
    unit DC gain in normalised units is one in physical units too."""
    for name, names in ((SERVO_STATE, state_names), (SERVO_INPUT, input_names)):
        if name not in names:
            raise KoopmanError(f"servo_lag needs {name!r} among the {'states' if names is state_names else 'inputs'}"
                               f" {tuple(names)}")
    i, j = list(state_names).index(SERVO_STATE), list(input_names).index(SERVO_INPUT)
    low = min(state_scaling.low[i], input_scaling.low[j])
    high = max(state_scaling.high[i], input_scaling.high[j])
    s_low, s_high = state_scaling.low.copy(), state_scaling.high.copy()
    u_low, u_high = input_scaling.low.copy(), input_scaling.high.copy()
    s_low[i], s_high[i], u_low[j], u_high[j] = low, high, low, high
    return MinMaxScaling(s_low, s_high), MinMaxScaling(u_low, u_high)


class MirrorKoopmanNet(KoopmanNet):
    """The scheduled deep Koopman network with the left / right mirror symmetry built in.

    ``state_parity`` (n_x,), ``dictionary_parity`` (n_dict,), ``input_parity`` (n_u,): +1 / -1;
    ``state_zero`` (n_x,), ``dictionary_zero`` (n_dict,), ``input_zero`` (n_u,): the normalised
    image of physical 0 of each channel. ``servo``: (state index, input index) of the wheel
    angle and the steer command, or None. ``steer_input``: index of the steer command whose
    bilinear term N (K, n_z, n_z) is learned, or None for none.
    """

    def __init__(self, n_x: int, n_u: int, n_features: int, hidden: Sequence[int], n_knots: int,
                 even_features: int, state_parity: np.ndarray, dictionary_parity: np.ndarray,
                 input_parity: np.ndarray, state_zero: np.ndarray, dictionary_zero: np.ndarray,
                 input_zero: np.ndarray, shared_rows: Sequence[int] = (),
                 servo: tuple[int, int] | None = None, steer_input: int | None = None) -> None:
        if n_knots < 2:
            raise KoopmanError("mirror symmetry is built for the scheduled form (speed knots)")
        if not 0 <= even_features <= n_features:
            raise KoopmanError(f"even_features={even_features} must be within 0..n_features={n_features}")
        super().__init__(n_x, n_u, n_features, hidden, len(dictionary_parity), False, n_knots, shared_rows)
        feature_parity = np.r_[np.ones(even_features), -np.ones(n_features - even_features)]
        parity = np.r_[state_parity, dictionary_parity, feature_parity]
        zero = np.r_[state_zero, dictionary_zero, np.zeros(n_features)]  # odd features vanish at 0
        as_tensor = lambda a: torch.as_tensor(np.asarray(a, dtype=float), dtype=torch.float32)  # noqa: E731
        self.register_buffer("state_parity", as_tensor(state_parity))
        self.register_buffer("state_zero", as_tensor(state_zero))
        self.register_buffer("feature_parity", as_tensor(feature_parity))
        self.register_buffer("odd_rows", as_tensor(parity < 0))
        self.register_buffer("lifted_zero", as_tensor(np.where(parity < 0, zero, 0.0)))
        self.register_buffer("input_zero", as_tensor(np.where(input_parity < 0, input_zero, 0.0)))
        self.register_buffer("A_mask", as_tensor(parity[:, None] == parity[None, :]))
        self.register_buffer("B_mask", as_tensor(parity[:, None] == np.asarray(input_parity)[None, :]))
        # The exact (float64) values, restored in ``export``: float32 rounding of the zeros would
        # leave the exported model a drift of ~1e-7.
        self._exact_buffers = {"state_zero": np.asarray(state_zero, dtype=float),
                               "lifted_zero": np.where(parity < 0, zero, 0.0),
                               "input_zero": np.where(np.asarray(input_parity) < 0, input_zero, 0.0)}
        self.servo = servo
        if servo is not None:
            # logit of the lag's pole per knot; 0.8 per 25 ms (a 0.11 s time constant) to start.
            self.servo_logit = nn.Parameter(torch.full((n_knots,), float(np.log(0.8 / 0.2))))
        self.steer_input = steer_input
        if steer_input is not None:
            if np.asarray(input_parity)[steer_input] >= 0:
                raise KoopmanError("the steer-bilinear term needs an odd (steer) input")
            n_mask = parity[:, None] != parity[None, :]  # even -> odd rows, odd -> even rows
            if servo is not None:
                n_mask[servo[0]] = False  # the wheel angle keeps its lag of unit DC gain
            self.register_buffer("N_mask", as_tensor(n_mask))
            # Zero to start: training begins at the warm-started model without the term.
            self.N_knots = nn.Parameter(torch.zeros(n_knots, self.n_z, self.n_z))

    @torch.no_grad()
    def warm_start(self, fit: dict[str, np.ndarray]) -> None:
        super().warm_start(fit)
        if self.servo is not None:  # the lag's pole from the least-squares fit of its row
            row = self.servo[0]
            pole = np.clip(np.asarray(fit["A"])[:, row, row], 0.05, 0.995)
            self.servo_logit.copy_(torch.as_tensor(np.log(pole / (1.0 - pole)), dtype=self.servo_logit.dtype))

    def mirror(self, x_n: torch.Tensor) -> torch.Tensor:
        """P x_n (..., n_x): the mirrored state in normalised units."""
        return torch.where(self.state_parity < 0, 2.0 * self.state_zero - x_n, x_n)

    def features(self, x_n: torch.Tensor) -> torch.Tensor:
        """x_n (..., n_x) -> Phi (..., d): even features first, then odd ones."""
        return 0.5 * (self.encoder(x_n) + self.feature_parity * self.encoder(self.mirror(x_n)))

    def knot_matrices(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A (K, n_z, n_z), B (K, n_z, n_u), c (K, n_z): masked by parity, the servo row set,
        and the odd rows of c fixed so that the centred model is equivariant."""
        A, B, c = super().knot_matrices()
        A, B = A * self.A_mask, B * self.B_mask
        if self.servo is not None:
            row, column = self.servo
            pole = torch.sigmoid(self.servo_logit)  # (K,)
            A = A.clone()
            B = B.clone()
            A[:, row] = 0.0
            A[:, row, row] = pole
            B[:, row] = 0.0
            B[:, row, column] = 1.0 - pole
        odd_c = self.lifted_zero - A @ self.lifted_zero - B @ self.input_zero  # (K, n_z)
        return A, B, torch.where(self.odd_rows > 0, odd_c, c)

    def bilinear_knots(self) -> torch.Tensor:
        """N (K, n_z, n_z) of the steer-bilinear term, masked by parity."""
        return self.N_knots * self.N_mask

    def rollout(self, z0: torch.Tensor, inputs_n: torch.Tensor, knot_weights: torch.Tensor | None = None,
                step_knot_weights: torch.Tensor | None = None) -> torch.Tensor:
        """As ``KoopmanNet.rollout``; with ``step_knot_weights`` (batch, n_steps, K) the odd
        rows take the matrices of each step's speed, the even rows those of the first. The
        steer-bilinear term, if any, is held at the first speed (as at run time)."""
        if step_knot_weights is None and self.steer_input is None:
            return super().rollout(z0, inputs_n, knot_weights)
        A_knots, B_knots, c_knots = self.knot_matrices()
        odd = self.odd_rows[:, None] > 0
        A_held = torch.einsum("bk,kij->bij", knot_weights, A_knots)
        forced = (torch.einsum("bk,kij,bsj->bsi", knot_weights, B_knots, inputs_n)
                  + (knot_weights @ c_knots)[:, None])
        if step_knot_weights is not None:
            forced_step = (torch.einsum("bsk,kij,bsj->bsi", step_knot_weights, B_knots, inputs_n)
                           + step_knot_weights @ c_knots)
            forced = torch.where(self.odd_rows > 0, forced_step, forced)
        if self.steer_input is not None:
            N = torch.einsum("bk,kij->bij", knot_weights, self.bilinear_knots())
            steer = inputs_n[..., self.steer_input] - self.input_zero[self.steer_input]  # (batch, n_steps)
        z, out = z0, []
        for i in range(inputs_n.shape[1]):
            A = (A_held if step_knot_weights is None
                 else torch.where(odd, torch.einsum("bk,kij->bij", step_knot_weights[:, i], A_knots), A_held))
            z_next = torch.einsum("bij,bj->bi", A, z) + forced[:, i]
            if self.steer_input is not None:
                z_next = z_next + steer[:, i, None] * torch.einsum("bij,bj->bi", N, z - self.lifted_zero)
            z = z_next
            out.append(z)
        return torch.stack(out, dim=1)

    def export(self, state_scaling: MinMaxScaling, input_scaling: MinMaxScaling,
               dictionary: tuple[str, ...] = (), dictionary_scaling: MinMaxScaling | None = None,
               speed_knots: tuple[float, ...] = ()) -> NormalisedKoopman:
        """An ordinary scheduled artefact: the two encoder passes folded into one MLP of twice
        the width (first layer [W1; W1 P], b [b1; b1 + W1 e] with P x_n = D x_n + e; hidden
        layers block-diagonal; last layer (W_L [h; h'] * (1, parity)) / 2)."""
        # In float64, so that the odd rows of c cancel to rounding (no drift left in float32).
        in_double = copy.deepcopy(self).double().cpu()
        for name, exact in self._exact_buffers.items():
            getattr(in_double, name).copy_(torch.as_tensor(exact, dtype=torch.float64))
        learned = KoopmanNet.export(in_double, state_scaling, input_scaling, dictionary, dictionary_scaling,
                                    speed_knots)
        layers = [(w.copy(), b.copy()) for w, b in learned.encoder]
        flip = self.state_parity.double().cpu().numpy()
        shift = np.where(flip < 0, 2.0 * self._exact_buffers["state_zero"], 0.0)
        parity = self.feature_parity.double().cpu().numpy()
        folded = []
        for i, (w, b) in enumerate(layers):
            if i == 0:
                w_new, b_new = np.vstack([w, w * flip[None, :]]), np.r_[b, b + w @ shift]
            elif i < len(layers) - 1:
                zero = np.zeros_like(w)
                w_new, b_new = np.block([[w, zero], [zero, w]]), np.r_[b, b]
            else:
                w_new, b_new = 0.5 * np.hstack([w, parity[:, None] * w]), 0.5 * (1.0 + parity) * b
            if len(layers) == 1:  # a single linear layer: input fold and output fold at once
                w_new = 0.5 * (w + parity[:, None] * w * flip[None, :])
                b_new = 0.5 * (b + parity * (b + w @ shift))
            folded.append((w_new, b_new))
        A_n, B_n, affine_n, N_n = learned.A_n, learned.B_n, learned.affine_n, None
        if self.steer_input is not None:
            A_n, B_n, affine_n, N_n = self._fold_bilinear(in_double, A_n, B_n, affine_n)
        return NormalisedKoopman(encoder=tuple(folded), A_n=A_n, B_n=B_n, N_n=N_n,
                                 state_scaling=state_scaling, input_scaling=input_scaling, dictionary=dictionary,
                                 dictionary_scaling=dictionary_scaling, affine_n=affine_n,
                                 speed_knots=learned.speed_knots)

    def _fold_bilinear(self, in_double: "MirrorKoopmanNet", A_n: np.ndarray, B_n: np.ndarray,
                       affine_n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The centred term (u_j - u0_j) N (z - z0) as the plain bilinear form's per-knot
        u_j N z: A_n - u0_j N, B_n[:, j] - N z0, affine_n + u0_j N z0; N_n (K, n_u, n_z, n_z)."""
        j = self.steer_input
        N = in_double.bilinear_knots().detach().numpy()  # (K, n_z, n_z), float64
        z0 = self._exact_buffers["lifted_zero"]
        u0 = self._exact_buffers["input_zero"][j]
        N_n = np.zeros((N.shape[0], B_n.shape[2], N.shape[1], N.shape[2]))
        N_n[:, j] = N
        B_n = B_n.copy()
        B_n[:, :, j] -= N @ z0
        return A_n - u0 * N, B_n, affine_n + u0 * (N @ z0), N_n

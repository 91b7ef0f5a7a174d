"""Deep Koopman model at run time: numpy only (no torch), cheap enough for a 25 ms loop.

Three model forms share this class (``form`` in the artefact):

- ``linear``, the paper's (eqs. 5-7): z+ = A z + B u + offset. Its response to a change of
  input does not depend on the state (superposition), so its yaw response to a steering
  step is the same at 10 and at 25 m/s (docs/koopman.md, "Why the model form").
- ``bilinear`` (control-affine Koopman, Bruder et al. 2021): z+ = A z + B u + offset +
  sum_j u_j N_j z, i.e. an input matrix B(z) = B + [N_1 z, ..., N_m z] that depends on the
  lifted state. Evaluated at the measured z_k the MPC's prediction stays linear in the
  inputs (``input_matrix``), so the MPC stays a QP.
- ``scheduled`` (a speed-scheduled lift, an LPV Koopman model): z+ = A(v) z + B(v) u +
  offset(v), the matrices interpolated linearly between speed knots, v the measured speed
  at the start of the prediction, held over it (as LMPC holds its bicycle's speed).
  ``at_speed(v)`` gives the linear model of that speed, so the MPC stays a QP. It may carry a
  bilinear term too, N(v) per knot (the mirror form's steer-bilinear term,
  ``models/koopman_train_symmetric.py``): ``at_speed(v)`` is then the bilinear model of
  that speed, whose B(z_k) the MPC holds over the horizon.

The lifted state is z = [x; psi(x); Phi(x)]: the physical state, an optional fixed
dictionary psi of physics-motivated functions (``DICTIONARY``: vy/vx, r/vx, vx r, vx^2,
the terms a single-track model is linear in) and the d learned features Phi of the encoder.
The model works in PHYSICAL units, ``x = C_P z`` with ``C_P = [I, 0]`` (eq. 7); the
network is trained in min-max normalised units, folded into these matrices when the
artefact is read (derivation in ``models/koopman_artifact.py``, which holds the learned
quantities as trained, ``NormalisedKoopman``, and writes the artefact, ``save_artifact``).
The fixed dictionary psi is in ``models/koopman_dictionary.py``. The names of both (and
``KoopmanError``, from ``models/errors.py``) stay importable from here.

``KoopmanModel`` can also be built directly from arrays (for tests of other packages): an
encoder with no layers gives a purely linear model ``z = x``.
"""
from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.errors import KoopmanError
from models.input_files import MODEL_FILE_MAX_BYTES, read_bounded
from models.koopman_artifact import DEFAULT_ARTIFACT, MinMaxScaling, NormalisedKoopman
from models.koopman_artifact import ARTIFACT_DIR, ARTIFACT_FORMAT, save_artifact  # noqa: F401 - re-exported
from models.koopman_dictionary import (DICTIONARY_FORMULAS, DICTIONARY_MIN_SPEED, check_dictionary,
                                       dictionary_features)
from models.koopman_dictionary import DICTIONARY, DICTIONARY_STATES  # noqa: F401 - re-exported

MODEL_FORMS = ("linear", "bilinear", "scheduled")
#: Default speed knots (m/s) of the scheduled form: denser where 1/vx changes fast.
DEFAULT_SPEED_KNOTS = (3.0, 6.0, 10.0, 15.0, 20.0, 27.0, 35.0)
#: Speed resolution (m/s) of the cached per-speed models of the scheduled form.
SPEED_QUANTUM = 0.05


def knot_weights(knots: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Hat-function weights of linear interpolation: speed (...,) -> (..., K), rows sum to 1.

    Speeds outside the knots take the end knot's matrices (no extrapolation).
    """
    knots = np.asarray(knots, dtype=float)
    v = np.clip(np.asarray(speed, dtype=float), knots[0], knots[-1])
    upper = np.clip(np.searchsorted(knots, v, side="right"), 1, len(knots) - 1)
    lower = upper - 1
    frac = (v - knots[lower]) / (knots[upper] - knots[lower])
    weights = np.zeros(v.shape + (len(knots),))
    np.put_along_axis(weights, lower[..., None], (1.0 - frac)[..., None], axis=-1)
    np.put_along_axis(weights, upper[..., None], frac[..., None], axis=-1)
    return weights


def first_non_finite(array: np.ndarray) -> str:
    """``VALUE at index (i, j)`` of an array's first entry that is not finite (for messages)."""
    flat = np.asarray(array).reshape(-1)
    position = int(np.flatnonzero(~np.isfinite(flat))[0])
    index = np.unravel_index(position, np.shape(array))
    return f"{flat[position]} at index {tuple(int(i) for i in index)}"


class KoopmanModel:
    """Lifted model ``z+ = A z + B u + offset (+ sum_j u_j N_j z)``, ``x = C_P z``, physical units.

    Attributes: ``A`` (n_z, n_z), ``B`` (n_z, n_u), ``offset`` (n_z,), ``N`` (n_u, n_z, n_z)
    (zeros for the linear form), ``form`` ("linear" | "bilinear"), ``dictionary`` (names of
    the fixed lifting functions), ``C_P`` (n_x, n_z), ``ts`` (s), ``n_x``, ``n_u``, ``n_z``,
    ``state_names``, ``input_names``, ``metadata`` (the artefact's JSON, or {} from arrays).
    """

    def __init__(
        self,
        A: np.ndarray,
        B: np.ndarray,
        offset: np.ndarray | None,
        encoder: Sequence[tuple[np.ndarray, np.ndarray]],
        ts: float,
        state_names: Sequence[str],
        input_names: Sequence[str],
        metadata: dict[str, Any] | None = None,
        *,
        bilinear: np.ndarray | None = None,
        dictionary: Sequence[str] = (),
        speed_knots: Sequence[float] = (),
    ) -> None:
        """Build from arrays in physical units.

        ``encoder``: [(W (h_out, h_in), b (h_out,)), ...] acting on the PHYSICAL state
        (normalisation already folded in), tanh after every layer but the last; the last
        layer gives the d learned features. An empty encoder means d = 0 (z = [x; psi]).
        ``bilinear``: N (n_u, n_z, n_z), or None for the linear form. ``dictionary``: names
        from ``DICTIONARY`` lifted between x and the learned features. ``speed_knots`` (K,)
        increasing: the scheduled form, A (K, n_z, n_z), B (K, n_z, n_u), offset (K, n_z)
        one per knot (and ``bilinear`` N (K, n_u, n_z, n_z) or None); ``A``/``B``/``offset``/
        ``N`` then hold the matrices of the first knot and ``at_speed(v)`` those of speed v.
        """
        self.state_names = tuple(state_names)
        self.input_names = tuple(input_names)
        self.n_x = len(self.state_names)
        self.n_u = len(self.input_names)
        self.speed_knots = np.asarray(speed_knots, dtype=float).reshape(-1)
        self.A_knots = self.B_knots = self.offset_knots = self.N_knots = None
        if self.speed_knots.size:
            if self.speed_knots.size < 2 or np.any(np.diff(self.speed_knots) <= 0):
                raise KoopmanError(f"speed knots must be >= 2 increasing speeds (of the first state, "
                                   f"{self.state_names[0]}), got {self.speed_knots}")
            self.A_knots = np.ascontiguousarray(A, dtype=float)
            self.B_knots = np.ascontiguousarray(B, dtype=float)
            self.offset_knots = np.ascontiguousarray(offset, dtype=float)
            if not (self.A_knots.ndim == 3 and len(self.A_knots) == self.speed_knots.size
                    and self.B_knots.shape[0] == self.speed_knots.size
                    and self.offset_knots.shape[0] == self.speed_knots.size):
                raise KoopmanError(f"a scheduled model needs one A, B, offset per knot ({self.speed_knots.size}), "
                                   f"got A {self.A_knots.shape}, B {self.B_knots.shape}, offset {self.offset_knots.shape}")
            A, B, offset = self.A_knots[0], self.B_knots[0], self.offset_knots[0]
            if bilinear is not None:
                self.N_knots = np.ascontiguousarray(bilinear, dtype=float)
                if self.N_knots.ndim != 4 or self.N_knots.shape[0] != self.speed_knots.size:
                    raise KoopmanError(f"a scheduled bilinear model needs one N per knot ({self.speed_knots.size}), "
                                       f"got N {self.N_knots.shape}")
                bilinear = self.N_knots[0]
        self.A = np.ascontiguousarray(A, dtype=float)
        self.B = np.ascontiguousarray(B, dtype=float)
        self.n_z = self.A.shape[0] if self.A.ndim == 2 else -1
        self.offset = (
            np.zeros(self.n_z) if offset is None else np.ascontiguousarray(offset, dtype=float).reshape(-1)
        )
        self._at_speed: dict[int, KoopmanModel] = {}
        self.ts = float(ts)
        self.metadata = dict(metadata or {})
        self.dictionary = check_dictionary(dictionary, self.state_names)
        self.form = "scheduled" if self.speed_knots.size else ("linear" if bilinear is None else "bilinear")
        self.N = (np.zeros((self.n_u, self.n_z, self.n_z)) if bilinear is None
                  else np.ascontiguousarray(bilinear, dtype=float))
        #: The learned quantities in normalised units when built by ``from_normalised``.
        self.normalised: NormalisedKoopman | None = None
        self._layers = [
            (np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(b, dtype=float).reshape(-1))
            for w, b in encoder
        ]
        self._validate()
        self.n_features = self.n_z - self.n_x - len(self.dictionary)
        self.C_P = np.hstack([np.eye(self.n_x), np.zeros((self.n_x, self.n_z - self.n_x))])
        # Work buffers for the single-state hot path (one per layer output).
        self._hidden = [np.empty(w.shape[0]) for w, _ in self._layers]

    def _validate(self) -> None:
        if self.n_x == 0 or self.n_u == 0:
            raise KoopmanError(f"need state and input names, got {self.state_names} / {self.input_names}")
        if self.A.ndim != 2 or self.A.shape[0] != self.A.shape[1] or self.A.shape[0] < self.n_x:
            raise KoopmanError(f"A must be square (n_z, n_z) with n_z >= n_x={self.n_x}, got {self.A.shape}")
        if self.B.shape != (self.n_z, self.n_u):
            raise KoopmanError(f"B must be (n_z, n_u)=({self.n_z}, {self.n_u}), got {self.B.shape}")
        if self.offset.shape != (self.n_z,):
            raise KoopmanError(f"offset must be (n_z,)=({self.n_z},), got {self.offset.shape}")
        if not (self.ts > 0 and np.isfinite(self.ts)):
            raise KoopmanError(f"ts must be a positive number of seconds, got {self.ts}")
        width = self.n_x
        for i, (w, b) in enumerate(self._layers):
            if w.ndim != 2 or w.shape[1] != width or b.shape != (w.shape[0],):
                raise KoopmanError(
                    f"encoder layer {i}: W {w.shape} / b {b.shape} do not take an input of width {width}"
                )
            width = w.shape[0]
        n_features = width if self._layers else 0
        if self.n_x + len(self.dictionary) + n_features != self.n_z:
            raise KoopmanError(
                f"n_z={self.n_z} != n_x={self.n_x} + dictionary {len(self.dictionary)} + encoder output {n_features}"
            )
        if self.N.shape != (self.n_u, self.n_z, self.n_z):
            raise KoopmanError(f"N must be (n_u, n_z, n_z)=({self.n_u}, {self.n_z}, {self.n_z}), got {self.N.shape}")
        layers = [(f"encoder layer {i} {part}", arr) for i, layer in enumerate(self._layers)
                  for part, arr in zip(("W", "b"), layer)]
        for name, arr in (("A", self.A), ("B", self.B), ("offset", self.offset), ("N", self.N),
                          ("A (knots)", self.A_knots), ("B (knots)", self.B_knots),
                          ("offset (knots)", self.offset_knots), ("N (knots)", self.N_knots),
                          ("speed knots", self.speed_knots), *layers):
            if arr is None:
                continue
            if not np.all(np.isfinite(arr)):
                raise KoopmanError(f"{name} has non-finite entries ({first_non_finite(arr)})")

    # ------------------------------------------------------------------ artefact I/O
    @classmethod
    def from_normalised(
        cls,
        learned: NormalisedKoopman,
        ts: float,
        state_names: Sequence[str],
        input_names: Sequence[str],
        metadata: dict[str, Any] | None = None,
    ) -> "KoopmanModel":
        """Build from the quantities as trained (normalised units); folds the scaling in."""
        encoder, A, B, offset, N = learned.to_physical()
        model = cls(A, B, offset, encoder, ts, state_names, input_names, metadata,
                    bilinear=N, dictionary=learned.dictionary, speed_knots=learned.speed_knots)
        model.normalised = learned
        return model

    @classmethod
    def load(cls, path: str | Path = DEFAULT_ARTIFACT) -> "KoopmanModel":
        """Load ``<name>.npz`` (weights) and ``<name>.json`` (metadata) written by training."""
        npz_path = Path(path)
        if npz_path.suffix != ".npz":
            npz_path = npz_path.with_suffix(".npz")
        json_path = npz_path.with_suffix(".json")
        for p in (npz_path, json_path):
            if not p.is_file():
                raise KoopmanError(f"Koopman artefact file not found: {p}")
        try:  # each file bounded before it is parsed (models/input_files.py)
            meta = json.loads(read_bounded(json_path, MODEL_FILE_MAX_BYTES, KoopmanError))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise KoopmanError(f"{json_path}: not readable JSON: {e}") from e
        try:
            with np.load(io.BytesIO(read_bounded(npz_path, MODEL_FILE_MAX_BYTES, KoopmanError))) as weights:
                arrays = {k: weights[k] for k in weights.files}
        except (OSError, ValueError, zipfile.BadZipFile) as e:
            raise KoopmanError(f"{npz_path}: not a readable .npz: {e}") from e
        for key, array in arrays.items():   # every array of the model finite, named
            if array.dtype.kind in "fc" and not np.all(np.isfinite(array)):
                raise KoopmanError(f"{npz_path}: array {key!r} has a non-finite entry "
                                   f"({first_non_finite(array)})")
        for key in ("ts", "state_names", "input_names", "state_min", "state_max", "input_min", "input_max",
                    "n_encoder_layers"):
            if key not in meta:
                raise KoopmanError(f"{json_path}: missing field {key!r}")
        try:
            encoder = tuple(
                (arrays[f"encoder_w{i}"], arrays[f"encoder_b{i}"]) for i in range(int(meta["n_encoder_layers"]))
            )
            form = meta.get("form", "linear")
            if form not in MODEL_FORMS:
                raise KoopmanError(f"{json_path}: form {form!r} is not one of {MODEL_FORMS}")
            dictionary = tuple(meta.get("dictionary", ()))
            learned = NormalisedKoopman(
                encoder=encoder,
                A_n=arrays["A_n"],
                B_n=arrays["B_n"],
                state_scaling=MinMaxScaling(np.array(meta["state_min"]), np.array(meta["state_max"])),
                input_scaling=MinMaxScaling(np.array(meta["input_min"]), np.array(meta["input_max"])),
                N_n=arrays["N_n"] if form == "bilinear" or "N_n" in arrays else None,
                affine_n=arrays.get("affine_n"),
                speed_knots=tuple(meta.get("speed_knots", ())) if form == "scheduled" else (),
                dictionary=dictionary,
                dictionary_scaling=(MinMaxScaling(np.array(meta["dictionary_min"]), np.array(meta["dictionary_max"]))
                                    if dictionary else None),
            )
        except KeyError as e:
            raise KoopmanError(f"{npz_path}: missing array {e}") from e
        return cls.from_normalised(learned, meta["ts"], meta["state_names"], meta["input_names"], meta)

    # ------------------------------------------------------------------ run time
    def lift(self, x: np.ndarray) -> np.ndarray:
        """Lifted state ``z = [x; Phi(x)]`` (eq. 6): x (..., n_x) -> z (..., n_z).

        A single state (n_x,) takes the hot path: preallocated buffers, in-place tanh.
        """
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (self.n_x,):
            raise KoopmanError(f"lift expects states of shape (..., {self.n_x}), got {x.shape}")
        if x.ndim == 1:
            return self._lift_one(x)
        z = np.empty(x.shape[:-1] + (self.n_z,))
        z[..., : self.n_x] = x
        n_known = self.n_x + len(self.dictionary)
        if self.dictionary:
            z[..., self.n_x : n_known] = dictionary_features(self.dictionary, x)
        if self._layers:
            h = x
            last = len(self._layers) - 1
            for i, (w, b) in enumerate(self._layers):
                h = h @ w.T + b
                if i < last:
                    np.tanh(h, out=h)
            z[..., n_known:] = h
        return z

    def _lift_one(self, x: np.ndarray) -> np.ndarray:
        z = np.empty(self.n_z)
        z[: self.n_x] = x
        n_known = self.n_x + len(self.dictionary)
        if self.dictionary:
            # Scalar arithmetic: a few ns each, where numpy calls cost a microsecond.
            vx = max(float(x[0]), DICTIONARY_MIN_SPEED)
            for i, name in enumerate(self.dictionary):
                z[self.n_x + i] = DICTIONARY_FORMULAS[name](float(x[0]), float(x[1]), float(x[2]), vx)
        h = x
        last = len(self._layers) - 1
        for i, ((w, b), out) in enumerate(zip(self._layers, self._hidden)):
            np.dot(w, h, out=out)  # np.dot: ~1 us less call overhead than matmul for a vector
            out += b
            if i < last:
                np.tanh(out, out=out)
            h = out
        if self._layers:
            z[n_known:] = h
        return z

    @property
    def scheduled_bilinear(self) -> bool:
        """True for the scheduled form with a bilinear term N(v)."""
        return self.N_knots is not None

    def at_speed(self, speed: float) -> "KoopmanModel":
        """The model of the scheduled form at ``speed`` (m/s, rounded to SPEED_QUANTUM, cached):
        linear, or bilinear with N(v) if the form has a bilinear term; any other form returns
        itself."""
        if self.form != "scheduled":
            return self
        key = round(float(np.clip(speed, self.speed_knots[0], self.speed_knots[-1])) / SPEED_QUANTUM)
        model = self._at_speed.get(key)
        if model is None:
            a, b, offset = self.matrices_for(np.asarray(key * SPEED_QUANTUM))
            model = KoopmanModel(a, b, offset, self._layers, self.ts, self.state_names,
                                 self.input_names, self.metadata, dictionary=self.dictionary,
                                 bilinear=self.bilinear_for(np.asarray(key * SPEED_QUANTUM)))
            if len(self._at_speed) > 2048:
                self._at_speed.clear()
            self._at_speed[key] = model
        return model

    def matrices_for(self, speed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A (..., n_z, n_z), B (..., n_z, n_u), offset (..., n_z) at speeds (...,) (exact, no rounding)."""
        if self.form != "scheduled":
            shape = np.shape(speed)
            return (np.broadcast_to(self.A, shape + self.A.shape), np.broadcast_to(self.B, shape + self.B.shape),
                    np.broadcast_to(self.offset, shape + self.offset.shape))
        weights = knot_weights(self.speed_knots, speed)
        return (np.tensordot(weights, self.A_knots, 1), np.tensordot(weights, self.B_knots, 1),
                weights @ self.offset_knots)

    def bilinear_for(self, speed: np.ndarray) -> np.ndarray | None:
        """N (..., n_u, n_z, n_z) at speeds (...,) of a scheduled bilinear model; N of any
        other bilinear model (broadcast); None without a bilinear term."""
        if self.N_knots is not None:
            return np.tensordot(knot_weights(self.speed_knots, speed), self.N_knots, 1)
        if self.form == "bilinear":
            return np.broadcast_to(self.N, np.shape(speed) + self.N.shape)
        return None

    def input_matrix(self, lifted_state: np.ndarray) -> np.ndarray:
        """B(z) = B + [N_1 z, ..., N_m z]: lifted_state (n_z,) -> (n_z, n_u).

        Frozen at the measured z_k over a horizon it makes the prediction linear in the
        inputs (the MPC stays a QP); equals ``B`` for the linear form.
        """
        if self.form == "linear":
            return self.B
        return self.B + (self.N @ lifted_state).T

    def step_lifted(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One step of eq. 5 with the affine (and bilinear) terms: z (..., n_z), u (..., n_u) -> (..., n_z)."""
        if self.form == "scheduled":  # the matrices of z's own speed
            A, B, offset = self.matrices_for(np.asarray(z)[..., 0])
            z_next = np.einsum("...ab,...b->...a", A, z) + np.einsum("...ab,...b->...a", B, u) + offset
            if self.N_knots is not None:
                z_next = z_next + np.einsum("...j,...jab,...b->...a", u, self.bilinear_for(np.asarray(z)[..., 0]), z)
            return z_next
        z_next = z @ self.A.T + u @ self.B.T + self.offset
        if self.form == "bilinear":
            z_next = z_next + np.einsum("...j,jab,...b->...a", u, self.N, z)
        return z_next

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Open-loop rollout in the lifted space from ``lift(x0)`` with the given inputs.

        x0 (batch, n_x), inputs (batch, n_steps, n_u) -> predicted states (batch, n_steps, n_x),
        entry [:, i] being x_{k+i+1}.
        """
        x0 = np.asarray(x0, dtype=float)
        inputs = np.asarray(inputs, dtype=float)
        if x0.ndim != 2 or x0.shape[1] != self.n_x:
            raise KoopmanError(f"predict expects x0 of shape (batch, {self.n_x}), got {x0.shape}")
        if inputs.ndim != 3 or inputs.shape[0] != x0.shape[0] or inputs.shape[2] != self.n_u:
            raise KoopmanError(
                f"predict expects inputs of shape ({x0.shape[0]}, n_steps, {self.n_u}), got {inputs.shape}"
            )
        z = self.lift(x0)
        if self.form == "scheduled":  # matrices of each start's speed, held (as the MPC does)
            A, B, offset = self.matrices_for(x0[:, 0])
            N = self.bilinear_for(x0[:, 0])
            forced = np.einsum("kab,ksb->ksa", B, inputs) + offset[:, None]
            out = np.empty((x0.shape[0], inputs.shape[1], self.n_x))
            for i in range(inputs.shape[1]):
                z_next = np.einsum("kab,kb->ka", A, z) + forced[:, i]
                if N is not None:
                    z_next += np.einsum("kj,kjac,kc->ka", inputs[:, i], N, z)
                z = z_next
                out[:, i] = z[:, : self.n_x]
            return out
        # The input contribution of all steps at once, then the cheap recursion.
        forced = inputs @ self.B.T + self.offset
        out = np.empty((x0.shape[0], inputs.shape[1], self.n_x))
        a_t = self.A.T
        for i in range(inputs.shape[1]):
            z_next = z @ a_t + forced[:, i]
            if self.form == "bilinear":
                z_next += np.einsum("bj,jac,bc->ba", inputs[:, i], self.N, z)
            z = z_next
            out[:, i] = z[:, : self.n_x]
        return out

    def spectral_radius(self) -> float:
        """Largest |eigenvalue| of A (unitless); close to but not above 1 for a stable plant."""
        if self.form == "scheduled":  # the largest over the knots
            return float(max(np.max(np.abs(np.linalg.eigvals(a))) for a in self.A_knots))
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))

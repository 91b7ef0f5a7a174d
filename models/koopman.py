"""Deep Koopman model at run time: numpy only (no torch), cheap enough for a 25 ms loop.

The network is trained in min-max normalised coordinates (``models/koopman_train.py``):

    x_n = D_x x + c_x,   u_n = D_u u + c_u                 (D = diag(1/(hi - lo)), c = -lo/(hi - lo))
    z_n = [x_n; Phi(x_n)]                                  (eq. 6 in normalised units)
    z_n+ = A_n z_n + B_n u_n                               (eq. 5)

This module works in PHYSICAL units. The lifted state keeps the physical state on top,
``z = [x; Phi(x_n)]`` so that ``x = C_P z`` with ``C_P = [I, 0]`` (eq. 7) holds in SI units.
With ``S = blkdiag(diag(hi_x - lo_x), I_d)`` and ``s = [lo_x; 0]`` we have ``z = S z_n + s``,
hence

    z+ = S z_n+ + s = S A_n S^-1 (z - s) + S B_n (D_u u + c_u) + s
       = A z + B u + offset

    A      = S A_n S^-1                                    (n_z, n_z)
    B      = S B_n D_u                                     (n_z, n_u)
    offset = s - A s + S B_n c_u                           (n_z,)

The affine term ``offset`` is the price of the affine normalisation; the ESO and the MPC
carry it as a known constant. The normalisation of the encoder input is folded into its
first layer (``W1' = W1 D_x``, ``b1' = b1 + W1 c_x``), so ``lift`` is plain matmuls.

``KoopmanModel`` can also be built directly from arrays (for tests of other packages): an
encoder with no layers gives a purely linear model ``z = x``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.errors import ModelError

ARTIFACT_DIR = Path(__file__).resolve().parent / "artifacts"
#: Default trained artefact (d = 5 learned features); the ``.json`` sits beside it.
DEFAULT_ARTIFACT = ARTIFACT_DIR / "dk_d5.npz"
#: Version of the artefact layout written by ``save_artifact``.
ARTIFACT_FORMAT = 1


class KoopmanError(ModelError):
    """A Koopman artefact or model definition is unusable (names the file / field)."""


@dataclass(frozen=True)
class MinMaxScaling:
    """Per-channel min-max bounds used in training: ``v_n = (v - low) / (high - low)``.

    ``low``, ``high``: shape (k,), ``high > low`` element-wise.
    """

    low: np.ndarray
    high: np.ndarray

    def __post_init__(self) -> None:
        low = np.asarray(self.low, dtype=float).reshape(-1)
        high = np.asarray(self.high, dtype=float).reshape(-1)
        if low.shape != high.shape:
            raise KoopmanError(f"min-max bounds differ in length: low {low.shape}, high {high.shape}")
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise KoopmanError(f"min-max bounds must be finite, got low={low}, high={high}")
        if np.any(high <= low):
            raise KoopmanError(f"min-max bounds need high > low, got low={low}, high={high}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    @property
    def scale(self) -> np.ndarray:
        """``1 / (high - low)``, shape (k,)."""
        return 1.0 / (self.high - self.low)

    @property
    def shift(self) -> np.ndarray:
        """``-low / (high - low)``, shape (k,)."""
        return -self.low / (self.high - self.low)

    def normalise(self, values: np.ndarray) -> np.ndarray:
        """(..., k) physical -> (..., k) normalised."""
        return (values - self.low) * self.scale


@dataclass(frozen=True)
class NormalisedKoopman:
    """The learned quantities as trained, in normalised units (what the ``.npz`` stores).

    ``encoder``: [(W (h_out, h_in), b (h_out,)), ...], tanh between layers, last layer linear,
    input x_n (n_x,), output Phi (d,). ``A_n`` (n_z, n_z), ``B_n`` (n_z, n_u), n_z = n_x + d.
    """

    encoder: tuple[tuple[np.ndarray, np.ndarray], ...]
    A_n: np.ndarray
    B_n: np.ndarray
    state_scaling: MinMaxScaling
    input_scaling: MinMaxScaling

    def to_physical(self) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray, np.ndarray]:
        """Fold the normalisation into the matrices (derivation in the module docstring).

        Returns (encoder acting on physical x, A (n_z, n_z), B (n_z, n_u), offset (n_z,)).
        """
        n_x = self.state_scaling.low.size
        n_z = self.A_n.shape[0]
        span = self.state_scaling.high - self.state_scaling.low
        s_diag = np.concatenate([span, np.ones(n_z - n_x)])
        s_vec = np.concatenate([self.state_scaling.low, np.zeros(n_z - n_x)])
        A = (s_diag[:, None] * self.A_n) / s_diag[None, :]
        SB = s_diag[:, None] * self.B_n
        B = SB * self.input_scaling.scale[None, :]
        offset = s_vec - A @ s_vec + SB @ self.input_scaling.shift
        encoder = [(np.array(w, dtype=float), np.array(b, dtype=float)) for w, b in self.encoder]
        if encoder:
            w0, b0 = encoder[0]
            encoder[0] = (w0 * self.state_scaling.scale[None, :], b0 + w0 @ self.state_scaling.shift)
        return encoder, A, B, offset


class KoopmanModel:
    """Lifted linear model ``z+ = A z + B u + offset``, ``x = C_P z``, in physical units.

    Attributes: ``A`` (n_z, n_z), ``B`` (n_z, n_u), ``offset`` (n_z,), ``C_P`` (n_x, n_z),
    ``ts`` (s), ``n_x``, ``n_u``, ``n_z``, ``state_names``, ``input_names``, ``metadata``
    (the artefact's JSON, or {} when built from arrays).
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
    ) -> None:
        """Build from arrays in physical units.

        ``encoder``: [(W (h_out, h_in), b (h_out,)), ...] acting on the PHYSICAL state
        (normalisation already folded in), tanh after every layer but the last; the last
        layer gives the d learned features. An empty encoder means d = 0 (z = x).
        """
        self.state_names = tuple(state_names)
        self.input_names = tuple(input_names)
        self.n_x = len(self.state_names)
        self.n_u = len(self.input_names)
        self.A = np.ascontiguousarray(A, dtype=float)
        self.B = np.ascontiguousarray(B, dtype=float)
        self.n_z = self.A.shape[0] if self.A.ndim == 2 else -1
        self.offset = (
            np.zeros(self.n_z) if offset is None else np.ascontiguousarray(offset, dtype=float).reshape(-1)
        )
        self.ts = float(ts)
        self.metadata = dict(metadata or {})
        #: The learned quantities in normalised units when built by ``from_normalised``.
        self.normalised: NormalisedKoopman | None = None
        self._layers = [
            (np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(b, dtype=float).reshape(-1))
            for w, b in encoder
        ]
        self._validate()
        self.n_features = self.n_z - self.n_x
        self.C_P = np.hstack([np.eye(self.n_x), np.zeros((self.n_x, self.n_features))])
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
        if self.n_x + n_features != self.n_z:
            raise KoopmanError(
                f"n_z={self.n_z} != n_x={self.n_x} + encoder output {n_features}"
            )
        for name, arr in (("A", self.A), ("B", self.B), ("offset", self.offset)):
            if not np.all(np.isfinite(arr)):
                raise KoopmanError(f"{name} has non-finite entries")

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
        encoder, A, B, offset = learned.to_physical()
        model = cls(A, B, offset, encoder, ts, state_names, input_names, metadata)
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
        try:
            meta = json.loads(json_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise KoopmanError(f"{json_path}: not readable JSON: {e}") from e
        try:
            with np.load(npz_path) as weights:
                arrays = {k: weights[k] for k in weights.files}
        except (OSError, ValueError) as e:
            raise KoopmanError(f"{npz_path}: not a readable .npz: {e}") from e
        for key in ("ts", "state_names", "input_names", "state_min", "state_max", "input_min", "input_max",
                    "n_encoder_layers"):
            if key not in meta:
                raise KoopmanError(f"{json_path}: missing field {key!r}")
        try:
            encoder = tuple(
                (arrays[f"encoder_w{i}"], arrays[f"encoder_b{i}"]) for i in range(int(meta["n_encoder_layers"]))
            )
            learned = NormalisedKoopman(
                encoder=encoder,
                A_n=arrays["A_n"],
                B_n=arrays["B_n"],
                state_scaling=MinMaxScaling(np.array(meta["state_min"]), np.array(meta["state_max"])),
                input_scaling=MinMaxScaling(np.array(meta["input_min"]), np.array(meta["input_max"])),
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
        if self._layers:
            h = x
            last = len(self._layers) - 1
            for i, (w, b) in enumerate(self._layers):
                h = h @ w.T + b
                if i < last:
                    np.tanh(h, out=h)
            z[..., self.n_x :] = h
        return z

    def _lift_one(self, x: np.ndarray) -> np.ndarray:
        z = np.empty(self.n_z)
        z[: self.n_x] = x
        h = x
        last = len(self._layers) - 1
        for i, ((w, b), out) in enumerate(zip(self._layers, self._hidden)):
            np.dot(w, h, out=out)  # np.dot: ~1 us less call overhead than matmul for a vector
            out += b
            if i < last:
                np.tanh(out, out=out)
            h = out
        if self._layers:
            z[self.n_x :] = h
        return z

    def step_lifted(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One step of eq. 5 with the affine term: z (..., n_z), u (..., n_u) -> (..., n_z)."""
        return z @ self.A.T + u @ self.B.T + self.offset

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
        # The input contribution of all steps at once, then the cheap recursion.
        forced = inputs @ self.B.T + self.offset
        out = np.empty((x0.shape[0], inputs.shape[1], self.n_x))
        a_t = self.A.T
        for i in range(inputs.shape[1]):
            z = z @ a_t + forced[:, i]
            out[:, i] = z[:, : self.n_x]
        return out

    def spectral_radius(self) -> float:
        """Largest |eigenvalue| of A (unitless); close to but not above 1 for a stable plant."""
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))


def save_artifact(
    path: str | Path,
    learned: NormalisedKoopman,
    metadata: dict[str, Any],
) -> tuple[Path, Path]:
    """Write ``<path>.npz`` (normalised weights) and ``<path>.json`` (metadata + bounds).

    ``metadata`` must hold ts, state_names and input_names; the bounds and layer count are
    added here from ``learned``. Returns (npz path, json path).
    """
    npz_path = Path(path).with_suffix(".npz")
    json_path = npz_path.with_suffix(".json")
    arrays: dict[str, np.ndarray] = {"A_n": np.asarray(learned.A_n), "B_n": np.asarray(learned.B_n)}
    for i, (w, b) in enumerate(learned.encoder):
        arrays[f"encoder_w{i}"] = np.asarray(w)
        arrays[f"encoder_b{i}"] = np.asarray(b)
    meta = dict(metadata)
    meta.update(
        format=ARTIFACT_FORMAT,
        n_encoder_layers=len(learned.encoder),
        activation="tanh",
        state_min=learned.state_scaling.low.tolist(),
        state_max=learned.state_scaling.high.tolist(),
        input_min=learned.input_scaling.low.tolist(),
        input_max=learned.input_scaling.high.tolist(),
    )
    npz_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(npz_path, **arrays)
    json_path.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return npz_path, json_path

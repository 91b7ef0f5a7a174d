"""The trained Koopman artefact: the learned quantities in normalised units, their fold into
physical units, and the files they are written to. numpy only.

The network is trained in min-max normalised coordinates (``models/koopman_train.py``):

    x_n = D_x x + c_x,   u_n = D_u u + c_u                 (D = diag(1/(hi - lo)), c = -lo/(hi - lo))
    z_n = [x_n; psi_n; Phi(x_n)]                           (eq. 6 in normalised units)
    z_n+ = A_n z_n + B_n u_n + sum_j u_n,j N_n,j z_n       (eq. 5; N_n = 0 in the linear form)

``NormalisedKoopman`` holds these quantities as trained (what the ``.npz`` stores) and folds
them into PHYSICAL units (``to_physical``, the matrices of ``models.koopman.KoopmanModel``).
The lifted state keeps the physical state on top, ``z = [x; Phi(x_n)]`` so that
``x = C_P z`` with ``C_P = [I, 0]`` (eq. 7) holds in SI units.
With ``S = blkdiag(diag(hi_x - lo_x), diag(hi_psi - lo_psi), I_d)`` and
``s = [lo_x; lo_psi; 0]`` we have ``z = S z_n + s``; with ``M_j = S N_n,j S^-1`` and
``u_n,j = d_j u_j + c_j``, hence

    z+ = S z_n+ + s = S A_n S^-1 (z - s) + S B_n (D_u u + c_u) + s + sum_j (d_j u_j + c_j) M_j (z - s)
       = A z + B u + offset + sum_j u_j N_j z

    A        = S A_n S^-1 + sum_j c_j M_j                  (n_z, n_z)
    N_j      = d_j M_j                                     (n_u, n_z, n_z) stacked
    B[:, j]  = d_j (S B_n[:, j] - M_j s)                   (n_z, n_u)
    offset   = s - A s + S B_n c_u                         (n_z,)

The affine term ``offset`` is the price of the affine normalisation; the ESO and the MPC
carry it as a known constant. The normalisation of the encoder input is folded into its
first layer (``W1' = W1 D_x``, ``b1' = b1 + W1 c_x``), so ``lift`` is plain matmuls.

``save_artifact`` writes ``<name>.npz`` (the normalised weights) and ``<name>.json`` (the
metadata and bounds); ``KoopmanModel.load`` reads them.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import KoopmanError

ARTIFACT_DIR = Path(__file__).resolve().parent / "artifacts"
#: Default trained artefact: ``make train``'s form, d = 8 learned features on 4 states (n_z = 12;
#: the file keeps the name of the first default, d = 5); the ``.json`` sits beside it.
DEFAULT_ARTIFACT = ARTIFACT_DIR / "dk_d5.npz"
#: Version of the artefact layout written by ``save_artifact``: 2 adds ``form``, ``dictionary``
#: and the bilinear ``N_n``; format-1 artefacts load as the linear form without dictionary.
ARTIFACT_FORMAT = 2


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
    #: Bilinear matrices (n_u, n_z, n_z), (K, n_u, n_z, n_z) scheduled; None for none.
    N_n: np.ndarray | None = None
    dictionary: tuple[str, ...] = ()
    #: Min-max bounds of the dictionary features (len(dictionary),); None without one.
    dictionary_scaling: MinMaxScaling | None = None
    #: Learned constant term c_n (n_z,) of the bilinear form (None: the paper's bias-free eq. 5).
    affine_n: np.ndarray | None = None
    #: Speed knots (K,) of the scheduled form; A_n, B_n, affine_n then carry a leading K axis.
    speed_knots: tuple[float, ...] = ()

    def to_physical(self) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray, np.ndarray,
                                   np.ndarray | None]:
        """Fold the normalisation into the matrices (derivation in the module docstring).

        Returns (encoder acting on physical x, A (n_z, n_z), B (n_z, n_u), offset (n_z,),
        N (n_u, n_z, n_z) or None). The scheduled form folds each knot alike (the weights
        sum to one, so interpolating the physical matrices interpolates the model): A (K,
        n_z, n_z), B (K, n_z, n_u), offset (K, n_z), N (K, n_u, n_z, n_z) or None.
        """
        if self.speed_knots:
            parts = [dataclasses.replace(self, A_n=self.A_n[m], B_n=self.B_n[m], speed_knots=(),
                                         affine_n=None if self.affine_n is None else self.affine_n[m],
                                         N_n=None if self.N_n is None else self.N_n[m])
                     .to_physical() for m in range(len(self.speed_knots))]
            encoder = parts[0][0]
            return (encoder, np.stack([p[1] for p in parts]), np.stack([p[2] for p in parts]),
                    np.stack([p[3] for p in parts]), None if self.N_n is None else np.stack([p[4] for p in parts]))
        n_z = self.A_n.shape[0]
        low, high = [self.state_scaling.low], [self.state_scaling.high]
        if self.dictionary_scaling is not None:
            low.append(self.dictionary_scaling.low)
            high.append(self.dictionary_scaling.high)
        low_known, high_known = np.concatenate(low), np.concatenate(high)
        n_known = low_known.size
        s_diag = np.concatenate([high_known - low_known, np.ones(n_z - n_known)])
        s_vec = np.concatenate([low_known, np.zeros(n_z - n_known)])
        A = (s_diag[:, None] * self.A_n) / s_diag[None, :]
        SB = s_diag[:, None] * self.B_n
        d_u, c_u = self.input_scaling.scale, self.input_scaling.shift
        B = SB * d_u[None, :]
        N = None
        if self.N_n is not None:
            M = (s_diag[None, :, None] * self.N_n) / s_diag[None, None, :]  # S N_n,j S^-1
            A = A + np.einsum("j,jab->ab", c_u, M)
            N = d_u[:, None, None] * M
            B = B - (M @ s_vec).T * d_u[None, :]
        offset = s_vec - A @ s_vec + SB @ c_u
        if self.affine_n is not None:
            offset = offset + s_diag * self.affine_n
        encoder = [(np.array(w, dtype=float), np.array(b, dtype=float)) for w, b in self.encoder]
        if encoder:
            w0, b0 = encoder[0]
            encoder[0] = (w0 * self.state_scaling.scale[None, :], b0 + w0 @ self.state_scaling.shift)
        return encoder, A, B, offset, N


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
    if learned.N_n is not None:
        arrays["N_n"] = np.asarray(learned.N_n)
    if learned.affine_n is not None:
        arrays["affine_n"] = np.asarray(learned.affine_n)
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
        form="scheduled" if learned.speed_knots else ("linear" if learned.N_n is None else "bilinear"),
        speed_knots=list(learned.speed_knots),
        dictionary=list(learned.dictionary),
    )
    if learned.dictionary_scaling is not None:
        meta.update(dictionary_min=learned.dictionary_scaling.low.tolist(),
                    dictionary_max=learned.dictionary_scaling.high.tolist())
    npz_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(npz_path, **arrays)
    json_path.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return npz_path, json_path

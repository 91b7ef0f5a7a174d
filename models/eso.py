"""Extended state observer (ESO) in the Koopman lifted space (paper Sec. II-B, eqs. 12-14,
Appendix A eqs. 23-24).

Model with the total disturbance ``w`` (eq. 12, plus our normalisation offset)::

    z[k+1] = A z[k] + B u[k] + offset + w[k]                              (12)

Observer, with ``z_tilde = z - z_hat`` (eq. 14)::

    z_hat[k+1] = A z_hat[k] + B u[k] + offset + w_hat[k] - beta1 g1(z_tilde[k])   (13)
    w_hat[k+1] = w_hat[k] - beta2 g2(z_tilde[k])

Error dynamics (Appendix A), g1 = g2 = identity and w constant, ``w_tilde = w - w_hat``::

    z_tilde[k+1] = z[k+1] - z_hat[k+1]
                 = (A z + B u + offset + w) - (A z_hat + B u + offset + w_hat - beta1 z_tilde)
                 = (A + beta1) z_tilde[k] + w_tilde[k]                     (23, first row)
    w_tilde[k+1] = w - w_hat[k+1] = w_tilde[k] + beta2 z_tilde[k]           (23, second row)

so ``[z_tilde; w_tilde][k+1] = Theta [z_tilde; w_tilde][k]`` with
``Theta = [[A + beta1, I], [beta2, I]]`` (eq. 24), and the errors vanish iff the spectral
radius of Theta is below 1. The minus signs in eq. 13 make the useful gains negative:
``A + beta1`` must be contracting and ``beta2`` must pull ``w_hat`` towards the residual.

The affine ``offset`` of our KoopmanModel (from min-max normalisation) is part of the
observer's model, so ``w_hat`` estimates only the modelling error and starts at zero; the
offset is known and never has to be learned online.

Run time only: plain numpy on arrays of a few elements. The pure ``eso_update`` is the one
implementation of eq. 13; ``ExtendedStateObserver`` merely holds its state.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from models.errors import ModelError

#: Correction function g(z_tilde) -> same shape (eq. 13); the paper uses the identity.
CorrectionFunction = Callable[[np.ndarray], np.ndarray]

#: Gain given as a scalar (times the identity) or a (n_z, n_z) matrix.
Gain = float | np.ndarray


#: Radii within this of 1 count as 1 (eigenvalues of Theta carry rounding errors of this size:
#: zero gains give an exact eigenvalue 1 that may be computed as 1 - 1e-16).
RADIUS_TOLERANCE = 1e-9


class EsoGainError(ModelError):
    """The observer gains give an error dynamics (eq. 24) that does not converge."""


class EsoShapeError(ModelError):
    """An observer matrix, gain or signal has the wrong shape or non-finite entries."""


def identity_correction(z_tilde: np.ndarray) -> np.ndarray:
    """g(z_tilde) = z_tilde, the paper's choice (Remark 1)."""
    return z_tilde


@dataclass(frozen=True)
class InnovationSaturation:
    """g2 of eq. 13 that bounds how far w_hat moves in one step (no windup on model breakdown).

    ``g2(z~) = z~ / s`` with ``s = max(1, max_i |z~[i]| / limit)`` over the ``rows`` of the
    physical lateral states (vy and yaw rate): the whole innovation vector is scaled down, its
    direction kept, once its vy or yaw-rate entry exceeds ``limit`` (m/s, rad/s per step).

    Why: the disturbance model holds w constant. A constant disturbance (an offset, a bank,
    a crosswind) leaves small, persistent one-step innovations once the transient is gone; a
    tyre at its friction limit leaves large ones that change sign with the manoeuvre, and
    integrating those at the full gain and holding them over the horizon made the low-mu lane
    change oscillate (docs/eso.md). Bounding the step keeps the slow part and drops the rest.
    With every innovation below the limit g2 is the identity and the error poles of eq. 24
    hold; ``limit`` 0 means no bound (the identity). Non-finite entries propagate.
    """

    rows: tuple[int, ...]
    limit: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.limit) and self.limit >= 0.0):
            raise EsoShapeError(f"innovation limit must be finite and >= 0, got {self.limit!r}")
        if not self.rows:
            raise EsoShapeError("innovation saturation needs at least one row")
        # The rows as an index array once, not a new list on every control step.
        object.__setattr__(self, "_index", np.array(self.rows, dtype=np.intp))

    def __call__(self, z_tilde: np.ndarray) -> np.ndarray:
        """(n_z,) -> (n_z,)."""
        return self.bounded(z_tilde, self.limit)

    def bounded(self, z_tilde: np.ndarray, limit: float) -> np.ndarray:
        """(n_z,) -> (n_z,): ``z_tilde`` scaled down to ``limit`` on the rows (0: as it is)."""
        if limit == 0.0:
            return z_tilde
        scale = float(np.max(np.abs(z_tilde[self._index]))) / limit
        return z_tilde / scale if scale > 1.0 else z_tilde  # NaN: not > 1, propagates


#: The widest the bound of ``PersistentInnovationBound`` grows, as a multiple of its limit.
PERSISTENCE_MAX_FACTOR = 4.0
#: Where the count of ``PersistentInnovationBound`` stops (the C core's int never overflows).
SATURATED_STEPS_MAX = 1_000_000


class PersistentInnovationBound:
    """g2 of eq. 13: ``InnovationSaturation`` whose bound widens while the innovation stays
    beyond it with one sign.

    The bound of a step is ``limit * min(PERSISTENCE_MAX_FACTOR, 1 + n / persistence_steps)``
    with ``n`` the number of consecutive steps, up to the last one advanced, whose innovation
    exceeded that step's bound with the same sign (the sign of its larger lateral entry,
    the first row on a tie). A step within the bound, a sign change or a restart sets ``n``
    back (to 0, or 1 for a new sign). ``persistence_steps`` 0 keeps the bound at ``limit``.

    Why: the fixed bound keeps the slow part of the innovation and drops the large, sign-
    changing one of a tyre at its limit, but it drops the large part of a large *constant*
    disturbance as well: w_hat then moves by at most ``beta2 * limit`` per step, and a
    0.02 rad steering offset at 50 km/h took longer than an 80 m straight to correct
    (results/disturbances.md). A constant disturbance keeps the innovation's sign until
    w_hat has caught up; a tyre at its limit changes it with the manoeuvre. The bound never
    grows beyond ``PERSISTENCE_MAX_FACTOR`` times the limit, so a saturated actuator (whose
    innovation also keeps its sign) still moves w_hat at a bounded rate.

    ``lateral_accel_gate`` (m/s^2; 0: none) keeps the widening to steady driving: a step
    whose measured lateral acceleration |vx r| is not below it restarts the count instead of
    advancing it. In a manoeuvre near the tyres' limit the innovation keeps one sign for
    long stretches too, and widening there made the tuning set's low-friction and crosswind
    drives worse (docs/eso.md); a steering offset or a crosswind on a straight shows at
    almost no lateral acceleration.

    The bound is the state of the observer of one controller: the controller's observer
    calls ``advance`` once per step with the step's innovation and lateral acceleration,
    after the update that used the bound, and ``restart`` when the observer restarts.
    """

    def __init__(self, rows: tuple[int, ...], limit: float, persistence_steps: float,
                 lateral_accel_gate: float = 0.0) -> None:
        self.saturation = InnovationSaturation(rows, limit)
        if not (math.isfinite(persistence_steps) and persistence_steps >= 0.0):
            raise EsoShapeError(f"innovation persistence must be finite and >= 0 steps, got {persistence_steps!r}")
        if not (math.isfinite(lateral_accel_gate) and lateral_accel_gate >= 0.0):
            raise EsoShapeError(f"widening's lateral acceleration gate must be finite and >= 0 m/s^2, "
                                f"got {lateral_accel_gate!r}")
        self.persistence_steps = float(persistence_steps)
        self.lateral_accel_gate = float(lateral_accel_gate)
        self.saturated_steps = 0
        self.sign = 0.0

    @property
    def widens(self) -> bool:
        """Whether ``advance`` can widen the bound (a widening and a bound are set)."""
        return self.persistence_steps > 0.0 and self.saturation.limit > 0.0

    @property
    def limit(self) -> float:
        """The bound of the next step (m/s, rad/s; 0: no bound)."""
        limit = self.saturation.limit
        if self.persistence_steps == 0.0 or self.saturated_steps == 0:
            return limit
        return limit * min(PERSISTENCE_MAX_FACTOR, 1.0 + self.saturated_steps / self.persistence_steps)

    def __call__(self, z_tilde: np.ndarray) -> np.ndarray:
        """(n_z,) -> (n_z,), with this step's bound."""
        return self.saturation.bounded(z_tilde, self.limit)

    def advance(self, z_tilde: np.ndarray, lateral_accel: float = 0.0) -> None:
        """Count the step whose innovation (n_z,) the bound just limited, at the measured
        lateral acceleration ``lateral_accel`` (m/s^2, vx times the yaw rate)."""
        if not self.widens:
            return
        # not below the gate (NaN included): a manoeuvre, not a steady disturbance
        if self.lateral_accel_gate > 0.0 and not abs(lateral_accel) < self.lateral_accel_gate:
            self.restart()
            return
        rows = self.saturation.rows
        peak_row = rows[0]
        for row in rows[1:]:
            if abs(float(z_tilde[row])) > abs(float(z_tilde[peak_row])):
                peak_row = row
        peak = float(z_tilde[peak_row])
        # the very test of InnovationSaturation.bounded (scale > 1), so that a step counts
        # exactly when the bound scaled it
        if not abs(peak) / self.limit > 1.0:  # NaN: not > 1
            self.restart()
            return
        sign = 1.0 if peak > 0.0 else -1.0
        same = sign == self.sign
        self.saturated_steps = min(self.saturated_steps + 1, SATURATED_STEPS_MAX) if same else 1
        self.sign = sign

    def restart(self) -> None:
        """Back to the limit (the observer restarted, or the innovation was within it)."""
        self.saturated_steps = 0
        self.sign = 0.0


def _gain_matrix(gain: Gain, n_z: int, name: str) -> np.ndarray:
    """Scalar -> scalar * I (n_z, n_z); matrix checked for shape and finiteness."""
    matrix = np.asarray(gain, dtype=float)
    if matrix.ndim == 0:
        matrix = float(matrix) * np.eye(n_z)
    if matrix.shape != (n_z, n_z):
        raise EsoShapeError(f"{name} must be a scalar or ({n_z}, {n_z}), got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise EsoShapeError(f"{name} has non-finite entries")
    return matrix


def _system_matrix(A: np.ndarray) -> np.ndarray:
    matrix = np.asarray(A, dtype=float)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise EsoShapeError(f"A must be square (n_z, n_z), got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise EsoShapeError("A has non-finite entries")
    return matrix


def theta_matrix(A: np.ndarray, beta1: Gain, beta2: Gain) -> np.ndarray:
    """Error-dynamics matrix of eq. 24, shape (2 n_z, 2 n_z).

    ``Theta = [[A + beta1, I], [beta2, I]]`` acting on ``[z_tilde; w_tilde]``;
    A (n_z, n_z), gains scalar or (n_z, n_z).
    """
    A = _system_matrix(A)
    n_z = A.shape[0]
    theta = np.empty((2 * n_z, 2 * n_z))
    identity = np.eye(n_z)
    theta[:n_z, :n_z] = A + _gain_matrix(beta1, n_z, "beta1")
    theta[:n_z, n_z:] = identity
    theta[n_z:, :n_z] = _gain_matrix(beta2, n_z, "beta2")
    theta[n_z:, n_z:] = identity
    return theta


def spectral_radius(A: np.ndarray, beta1: Gain, beta2: Gain) -> float:
    """Spectral radius of Theta (eq. 24): max |eigenvalue|; below 1 means convergence."""
    return float(np.max(np.abs(np.linalg.eigvals(theta_matrix(A, beta1, beta2)))))


def _frozen_copy(array: np.ndarray) -> np.ndarray:
    copy = np.array(array, dtype=float, copy=True)
    copy.setflags(write=False)
    return copy


@dataclass(frozen=True, eq=False)
class EsoParams:
    """Observer model and gains of eq. 13, validated on construction.

    A (n_z, n_z), B (n_z, n_u), offset (n_z,) in physical units (the KoopmanModel's);
    ``bilinear`` N (n_u, n_z, n_z) of a bilinear model, else None: the observer's model
    input is then B(z_k) u = B u + sum_j u_j N_j z_k with the MEASURED z_k (as the MPC);
    beta1, beta2 scalars or (n_z, n_z) matrices, stored as (n_z, n_z) matrices; g1, g2
    correction functions (identity by default). ``spectral_radius`` is that of Theta
    (eq. 24); gains giving a radius >= 1 raise ``EsoGainError`` naming the radius.
    """

    A: np.ndarray
    B: np.ndarray
    offset: np.ndarray
    beta1: Gain
    beta2: Gain
    g1: CorrectionFunction = identity_correction
    g2: CorrectionFunction = identity_correction
    bilinear: np.ndarray | None = None
    spectral_radius: float = field(init=False)
    update_matrix: np.ndarray = field(init=False, repr=False)
    update_offset: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        A = _system_matrix(self.A)
        n_z = A.shape[0]
        B = np.asarray(self.B, dtype=float)
        if B.ndim != 2 or B.shape[0] != n_z:
            raise EsoShapeError(f"B must be ({n_z}, n_u), got shape {B.shape}")
        offset = np.asarray(self.offset, dtype=float)
        if offset.shape != (n_z,):
            raise EsoShapeError(f"offset must be ({n_z},), got shape {offset.shape}")
        for name, value in (("B", B), ("offset", offset)):
            if not np.all(np.isfinite(value)):
                raise EsoShapeError(f"{name} has non-finite entries")
        if self.bilinear is not None:
            bilinear = np.asarray(self.bilinear, dtype=float)
            if bilinear.shape != (B.shape[1], n_z, n_z) or not np.all(np.isfinite(bilinear)):
                raise EsoShapeError(f"bilinear must be finite ({B.shape[1]}, {n_z}, {n_z}), got shape {bilinear.shape}")
            object.__setattr__(self, "bilinear", _frozen_copy(bilinear))
        if not (callable(self.g1) and callable(self.g2)):
            raise EsoShapeError("g1 and g2 must be callables mapping (n_z,) -> (n_z,)")
        beta1 = _gain_matrix(self.beta1, n_z, "beta1")
        beta2 = _gain_matrix(self.beta2, n_z, "beta2")
        radius = spectral_radius(A, beta1, beta2)
        if not radius < 1.0 - RADIUS_TOLERANCE:
            raise EsoGainError(
                f"ESO gains refused: spectral radius of Theta (eq. 24) is {radius:.6g}, "
                "must be < 1 for the estimation errors to converge"
            )
        # Frozen dataclass: store the normalised, read-only arrays in place of the inputs.
        object.__setattr__(self, "A", _frozen_copy(A))
        object.__setattr__(self, "B", _frozen_copy(B))
        object.__setattr__(self, "offset", _frozen_copy(offset))
        object.__setattr__(self, "beta1", _frozen_copy(beta1))
        object.__setattr__(self, "beta2", _frozen_copy(beta2))
        object.__setattr__(self, "spectral_radius", radius)
        # eq. 13 on the stacked vector [z_hat; w_hat; u; g1(z~); g2(z~)] (see eso_update).
        n_u = B.shape[1]
        identity = np.eye(n_z)
        zeros = np.zeros((n_z, n_z))
        update = np.block([
            [A, identity, B, -beta1, zeros],
            [zeros, identity, np.zeros((n_z, n_u)), zeros, -beta2],
        ])
        object.__setattr__(self, "update_matrix", _frozen_copy(update))
        object.__setattr__(self, "update_offset", _frozen_copy(np.concatenate([offset, np.zeros(n_z)])))

    @property
    def n_z(self) -> int:
        """Lifted dimension."""
        return self.A.shape[0]

    @property
    def n_u(self) -> int:
        """Number of inputs."""
        return self.B.shape[1]


@dataclass(frozen=True, eq=False)
class EsoState:
    """Observer state: lifted state estimate z_hat (n_z,) and disturbance estimate w_hat (n_z,)."""

    lifted_state_estimate: np.ndarray
    disturbance_estimate: np.ndarray


def initial_state(lifted_measurement: np.ndarray, params: EsoParams) -> EsoState:
    """Start at the measured lifted state (n_z,) with zero disturbance: z_tilde[0] = 0."""
    z0 = np.asarray(lifted_measurement, dtype=float)
    if z0.shape != (params.n_z,):
        raise EsoShapeError(f"initial lifted state must be ({params.n_z},), got shape {z0.shape}")
    if not np.all(np.isfinite(z0)):
        raise EsoShapeError("initial lifted state has non-finite entries")
    return EsoState(z0.copy(), np.zeros(params.n_z))


def eso_update(
    state: EsoState, lifted_measurement: np.ndarray, u: np.ndarray, params: EsoParams
) -> EsoState:
    """One step of eq. 13: (z_hat[k], w_hat[k]), z[k] (n_z,), u[k] (n_u,) -> step k+1.

    Never raises on bad values (it runs in the control loop): a non-finite measurement or
    input, or a step whose result would be non-finite, returns ``state`` itself unchanged.
    Shapes are the caller's contract and are not re-checked here (hot path); g1 and g2 must
    map non-finite entries to non-finite entries (any element-wise numpy expression does).
    The returned arrays are views of one buffer: treat them as read-only.
    """
    lifted_measurement = np.asarray(lifted_measurement, dtype=float)
    u = np.asarray(u, dtype=float)
    z_tilde = lifted_measurement - state.lifted_state_estimate  # eq. 14
    # eq. 13 as one product: [z_hat+; w_hat+] = F [z_hat; w_hat; u; g1(z~); g2(z~)] + [offset; 0]
    # (F built once in EsoParams), so a step is a handful of numpy calls on ~30 numbers.
    stacked = np.concatenate(
        (state.lifted_state_estimate, state.disturbance_estimate, u, params.g1(z_tilde), params.g2(z_tilde))
    )
    # One dot product checks every entry at once (NaN/inf propagate into it); it also
    # rejects absurd magnitudes (> ~1e154) whose square overflows.
    if not math.isfinite(stacked @ stacked):
        return state
    next_stacked = params.update_matrix @ stacked + params.update_offset
    if params.bilinear is not None:  # B(z_k) u: the input matrix at the measured z_k
        next_stacked[: params.n_z] += u @ (params.bilinear @ lifted_measurement)
    if not math.isfinite(next_stacked @ next_stacked):
        return state
    return EsoState(next_stacked[: params.n_z], next_stacked[params.n_z :])


def innovated_disturbance(
    state: EsoState, lifted_measurement: np.ndarray, params: EsoParams
) -> np.ndarray:
    """w_hat[k+1] (n_z,) from z[k] before u[k] is known (it does not depend on u).

    An MPC deciding u[k] at cycle k can use the estimate that already includes z[k]
    instead of the one from the previous cycle; equals ``eso_update(...)
    .disturbance_estimate``. Non-finite measurement -> the current estimate.
    """
    z_tilde = np.asarray(lifted_measurement, dtype=float) - state.lifted_state_estimate
    if not math.isfinite(z_tilde @ z_tilde):
        return state.disturbance_estimate
    w_next = state.disturbance_estimate - params.beta2 @ params.g2(z_tilde)
    return w_next if math.isfinite(w_next @ w_next) else state.disturbance_estimate


@dataclass(frozen=True)
class EsoGains:
    """Result of ``design_gains``: beta1, beta2 (n_z, n_z) or scalars, the error poles
    targeted and the spectral radius of Theta actually obtained."""

    beta1: Gain
    beta2: Gain
    target_poles: tuple[float, float]
    spectral_radius: float


def pole_from_bandwidth(bandwidth_hz: float, ts: float) -> float:
    """Discrete pole exp(-2 pi f ts) of a first-order error decay with bandwidth f."""
    if not (bandwidth_hz > 0 and ts > 0):
        raise EsoShapeError(f"bandwidth_hz and ts must be > 0, got {bandwidth_hz}, {ts}")
    return math.exp(-2.0 * math.pi * bandwidth_hz * ts)


def design_gains(
    A: np.ndarray,
    pole: float | None = None,
    *,
    bandwidth_hz: float | None = None,
    ts: float | None = None,
    second_pole: float | None = None,
    structure: str = "matrix",
) -> EsoGains:
    """Gains placing the error poles of eq. 24 at ``pole`` and ``second_pole``.

    Per eigen-direction of ``A + beta1`` (scalar or commuting gains) Theta reduces to
    ``[[a + b1, 1], [b2, 1]]`` with characteristic polynomial
    ``l^2 - (a + b1 + 1) l + (a + b1 - b2)``. Matching ``(l - p1)(l - p2)`` gives
    ``a + b1 = p1 + p2 - 1`` and ``b2 = -(1 - p1)(1 - p2)``.

    ``structure="matrix"``: ``beta1 = (p1 + p2 - 1) I - A``, ``beta2 = -(1-p1)(1-p2) I``;
    every block of Theta is then a multiple of I, so its eigenvalues are exactly p1, p2
    whatever A is. ``structure="scalar"``: beta1 a scalar matched to the mean of A's
    eigenvalues' real parts; the other modes land elsewhere, and the radius reported says
    where. Give ``pole`` in [0, 1) directly, or ``bandwidth_hz`` and ``ts``; the second
    pole defaults to the first (critically damped error response).
    """
    A = _system_matrix(A)
    if pole is None:
        if bandwidth_hz is None or ts is None:
            raise EsoShapeError("design_gains needs pole, or bandwidth_hz and ts")
        pole = pole_from_bandwidth(bandwidth_hz, ts)
    p1 = float(pole)
    p2 = p1 if second_pole is None else float(second_pole)
    for name, p in (("pole", p1), ("second_pole", p2)):
        if not 0.0 <= p < 1.0:
            raise EsoShapeError(f"{name} must be in [0, 1), got {p}")
    beta2_scalar = -(1.0 - p1) * (1.0 - p2)
    n_z = A.shape[0]
    if structure == "matrix":
        beta1: Gain = (p1 + p2 - 1.0) * np.eye(n_z) - A
        beta2: Gain = beta2_scalar * np.eye(n_z)
    elif structure == "scalar":
        beta1 = p1 + p2 - 1.0 - float(np.mean(np.linalg.eigvals(A).real))
        beta2 = beta2_scalar
    else:
        raise EsoShapeError(f"structure must be 'matrix' or 'scalar', got {structure!r}")
    return EsoGains(beta1, beta2, (p1, p2), spectral_radius(A, beta1, beta2))


class ExtendedStateObserver:
    """Stateful wrapper around ``eso_update``: holds the state, exposes reset / update."""

    def __init__(self, params: EsoParams) -> None:
        self.params = params
        self.state = initial_state(np.zeros(params.n_z), params)

    def reset(self, z0: np.ndarray) -> None:
        """Restart at the lifted state z0 (n_z,) with zero disturbance estimate."""
        self.state = initial_state(z0, self.params)

    def update(self, z: np.ndarray, u: np.ndarray) -> bool:
        """Advance by one step with lifted measurement z (n_z,) and input u (n_u,).

        Returns False (state untouched) when the measurement or input is non-finite; a
        wrong shape is a wiring error and raises ``EsoShapeError``.
        """
        z = np.asarray(z, dtype=float)
        u = np.asarray(u, dtype=float)
        if z.shape != (self.params.n_z,) or u.shape != (self.params.n_u,):
            raise EsoShapeError(
                f"update expects z ({self.params.n_z},) and u ({self.params.n_u},), "
                f"got {z.shape} and {u.shape}"
            )
        new_state = eso_update(self.state, z, u, self.params)
        accepted = new_state is not self.state
        self.state = new_state
        return accepted

    @property
    def disturbance_estimate(self) -> np.ndarray:
        """w_hat (n_z,)."""
        return self.state.disturbance_estimate

    @property
    def lifted_state_estimate(self) -> np.ndarray:
        """z_hat (n_z,)."""
        return self.state.lifted_state_estimate

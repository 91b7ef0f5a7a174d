"""Extended state observer in the lifted space (models/eso.py, paper eqs. 12-14, 23-24)."""
from __future__ import annotations

import timeit

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.errors import ModelError
from models.eso import (
    EsoGainError,
    EsoParams,
    EsoShapeError,
    EsoState,
    ExtendedStateObserver,
    design_gains,
    eso_update,
    initial_state,
    innovated_disturbance,
    pole_from_bandwidth,
    spectral_radius,
    theta_matrix,
)

N_Z = 6
N_U = 2


def linear_system(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A lifted-space-like system: A near I (slow discrete modes, spectral radius 0.98 so
    the simulated truth stays bounded), B (N_Z, N_U), offset (N_Z,)."""
    rng = np.random.default_rng(seed)
    A = np.eye(N_Z) + 0.03 * rng.standard_normal((N_Z, N_Z))
    A *= 0.98 / np.max(np.abs(np.linalg.eigvals(A)))
    B = 0.1 * rng.standard_normal((N_Z, N_U))
    offset = 0.05 * rng.standard_normal(N_Z)
    return A, B, offset


def simulate(
    params: EsoParams,
    A: np.ndarray,
    B: np.ndarray,
    offset: np.ndarray,
    disturbance: np.ndarray,
    seed: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """True system z+ = A z + B u + offset + w[k] driven by bounded random inputs, observed
    by the ESO started at the true z0 with w_hat = 0.

    disturbance (n_steps, N_Z) -> (true w (n_steps, N_Z), w_hat after each step (n_steps, N_Z)).
    """
    rng = np.random.default_rng(seed)
    z = rng.standard_normal(N_Z)
    state = initial_state(z, params)
    estimates = np.empty_like(disturbance)
    for k, w in enumerate(disturbance):
        u = rng.uniform(-1.0, 1.0, N_U)
        state = eso_update(state, z, u, params)
        z = A @ z + B @ u + offset + w
        estimates[k] = state.disturbance_estimate
    return disturbance, estimates


def test_theta_matches_independent_block_construction() -> None:
    A, _, _ = linear_system()
    rng = np.random.default_rng(5)
    beta1 = -np.eye(N_Z) - 0.1 * rng.standard_normal((N_Z, N_Z))
    beta2 = -0.2 * np.eye(N_Z)
    identity = np.eye(N_Z)
    expected = np.block([[A + beta1, identity], [beta2, identity]])
    theta = theta_matrix(A, beta1, beta2)
    radius = spectral_radius(A, beta1, beta2)
    independent = max(abs(np.linalg.eigvals(expected)))
    print(f"Theta max abs diff {np.max(np.abs(theta - expected)):.3g}; radius {radius:.12f} "
          f"vs independent {independent:.12f}")
    assert np.array_equal(theta, expected)
    assert radius == pytest.approx(independent, abs=1e-12)
    # Scalar gains mean scalar * I.
    scalar = theta_matrix(A, -0.9, -0.1)
    assert np.array_equal(scalar, np.block([[A - 0.9 * identity, identity], [-0.1 * identity, identity]]))


def test_error_dynamics_follow_theta() -> None:
    """The derivation in the module docstring: [z~; w~] evolves by Theta for constant w."""
    A, B, offset = linear_system()
    gains = design_gains(A, 0.7, second_pole=0.4)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    theta = theta_matrix(A, gains.beta1, gains.beta2)
    rng = np.random.default_rng(2)
    w = rng.standard_normal(N_Z)
    z = rng.standard_normal(N_Z)
    state = EsoState(z + rng.standard_normal(N_Z), rng.standard_normal(N_Z))
    error = np.concatenate([z - state.lifted_state_estimate, w - state.disturbance_estimate])
    worst = 0.0
    for _ in range(20):
        u = rng.uniform(-1, 1, N_U)
        state = eso_update(state, z, u, params)
        z = A @ z + B @ u + offset + w
        error = theta @ error
        measured = np.concatenate([z - state.lifted_state_estimate, w - state.disturbance_estimate])
        worst = max(worst, float(np.max(np.abs(measured - error))))
    print(f"max |error - Theta^k error0| over 20 steps: {worst:.3g}")
    assert worst < 1e-10


def test_constant_disturbance_is_estimated() -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    w_true = np.array([0.3, -0.2, 0.05, 0.0, 0.1, -0.4])
    true, estimated = simulate(params, A, B, offset, np.tile(w_true, (120, 1)))
    errors = np.max(np.abs(estimated - true), axis=1)
    print(f"|w_hat - w| after 10 / 40 / 120 steps: {errors[9]:.3g} / {errors[39]:.3g} / {errors[-1]:.3g}")
    assert errors[-1] < 1e-9
    assert errors[39] < errors[9]


def test_slowly_varying_disturbance_error_stays_bounded() -> None:
    """With w varying, e+ = Theta e + [0; w[k+1] - w[k]], so
    max |w~| <= sum_j ||Theta^j||_2 * max ||w[k+1] - w[k]||_2 (e0 = 0 since w[0] = 0)."""
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    steps = 400
    t = np.arange(steps) * 0.025
    amplitudes = np.array([0.3, -0.2, 0.1, 0.2, -0.1, 0.05])
    disturbance = amplitudes * np.sin(2 * np.pi * 0.5 * t)[:, None]  # 0.5 Hz
    true, estimated = simulate(params, A, B, offset, disturbance)
    # w_hat after step k estimates w[k] (eq. 13 uses z[k] and u[k]; z[k+1] has w[k]).
    observed = float(np.max(np.linalg.norm(estimated[1:] - true[:-1], axis=1)))
    theta = theta_matrix(A, gains.beta1, gains.beta2)
    power, gain_sum = np.eye(2 * N_Z), 0.0
    for _ in range(3000):
        gain_sum += np.linalg.norm(power, 2)
        power = theta @ power
    max_change = float(np.max(np.linalg.norm(np.diff(disturbance, axis=0), axis=1)))
    bound = gain_sum * max_change
    print(f"slowly varying w (0.5 Hz, |w| <= {np.linalg.norm(amplitudes):.3f}): "
          f"max |w_hat - w| = {observed:.4f}, bound sum||Theta^j|| * max|dw| = "
          f"{gain_sum:.2f} * {max_change:.4f} = {bound:.4f}")
    assert observed <= bound
    # and it tracks: the error is a fraction of the disturbance itself
    assert observed < 0.5 * np.linalg.norm(amplitudes)


@pytest.mark.parametrize(
    "beta1, beta2",
    [(0.0, 0.0), (0.5, -0.1), (-1.0, 0.1), (-1.0, -4.0)],
    ids=["no-correction", "positive-beta1", "positive-beta2", "beta2-too-large"],
)
def test_gains_with_radius_at_least_one_are_refused(beta1: float, beta2: float) -> None:
    A, B, offset = linear_system()
    radius = spectral_radius(A, beta1, beta2)
    print(f"beta1={beta1}, beta2={beta2}: radius {radius:.4f}")
    assert radius >= 1.0
    with pytest.raises(EsoGainError, match=f"spectral radius of Theta .* is {radius:.6g}") as info:
        EsoParams(A, B, offset, beta1, beta2)
    assert isinstance(info.value, ModelError)


def test_design_gains_place_the_poles() -> None:
    A, _, _ = linear_system()
    gains = design_gains(A, 0.8, second_pole=0.5)
    eigenvalues = np.sort(np.abs(np.linalg.eigvals(theta_matrix(A, gains.beta1, gains.beta2))))
    print(f"matrix gains, poles (0.8, 0.5): radius {gains.spectral_radius:.12f}, "
          f"|eigs| min {eigenvalues[0]:.6f} max {eigenvalues[-1]:.6f}")
    assert gains.spectral_radius == pytest.approx(0.8, abs=1e-9)
    assert eigenvalues[0] == pytest.approx(0.5, abs=1e-9)
    by_bandwidth = design_gains(A, bandwidth_hz=2.0, ts=0.025)
    assert by_bandwidth.target_poles[0] == pytest.approx(np.exp(-2 * np.pi * 2.0 * 0.025))
    assert by_bandwidth.spectral_radius < 1.0
    scalar = design_gains(A, 0.6, structure="scalar")
    independent = max(abs(np.linalg.eigvals(theta_matrix(A, scalar.beta1, scalar.beta2))))
    print(f"scalar gains beta1={scalar.beta1:.4f}, beta2={scalar.beta2:.4f}: target 0.6, "
          f"radius obtained {scalar.spectral_radius:.4f}")
    assert np.ndim(scalar.beta1) == 0
    assert scalar.spectral_radius == pytest.approx(independent)
    for bad in (dict(pole=1.0), dict(pole=-0.1), dict(), dict(pole=0.5, structure="diagonal")):
        with pytest.raises(EsoShapeError):
            design_gains(A, **bad)
    assert pole_from_bandwidth(1.0, 0.025) == pytest.approx(np.exp(-0.05 * np.pi))


def test_no_nan_from_finite_input() -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.5)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    rng = np.random.default_rng(7)
    observer = ExtendedStateObserver(params)
    observer.reset(rng.standard_normal(N_Z))
    for _ in range(2000):
        assert observer.update(rng.normal(0, 10, N_Z), rng.uniform(-1e3, 1e3, N_U))
        assert np.all(np.isfinite(observer.disturbance_estimate))
        assert np.all(np.isfinite(observer.lifted_state_estimate))
    print(f"2000 random finite steps: max |w_hat| {np.max(np.abs(observer.disturbance_estimate)):.3g}")


@settings(max_examples=60, deadline=None)
@given(
    z=st.lists(st.floats(-1e6, 1e6), min_size=N_Z, max_size=N_Z),
    u=st.lists(st.floats(-1e6, 1e6), min_size=N_U, max_size=N_U),
)
def test_any_finite_step_is_finite_and_accepted(z: list[float], u: list[float]) -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.5)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    state = initial_state(np.zeros(N_Z), params)
    new = eso_update(state, np.array(z), np.array(u), params)
    assert new is not state
    assert np.all(np.isfinite(new.lifted_state_estimate)) and np.all(np.isfinite(new.disturbance_estimate))


def test_reset_restores_initial_behaviour() -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    observer = ExtendedStateObserver(EsoParams(A, B, offset, gains.beta1, gains.beta2))
    rng = np.random.default_rng(3)
    z0 = rng.standard_normal(N_Z)
    measurements = rng.standard_normal((50, N_Z))
    inputs = rng.standard_normal((50, N_U))

    def run() -> np.ndarray:
        observer.reset(z0)
        assert np.array_equal(observer.lifted_state_estimate, z0)
        assert np.array_equal(observer.disturbance_estimate, np.zeros(N_Z))
        out = []
        for z, u in zip(measurements, inputs):
            observer.update(z, u)
            out.append(observer.disturbance_estimate.copy())
        return np.array(out)

    first = run()
    second = run()
    print(f"after reset, max |difference| of 50 estimates: {np.max(np.abs(first - second)):.3g}")
    assert np.array_equal(first, second)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_measurement_is_rejected(bad: float) -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    observer = ExtendedStateObserver(params)
    rng = np.random.default_rng(4)
    observer.reset(rng.standard_normal(N_Z))
    for _ in range(5):
        assert observer.update(rng.standard_normal(N_Z), rng.standard_normal(N_U))
    before_z = observer.lifted_state_estimate.copy()
    before_w = observer.disturbance_estimate.copy()
    measurement = rng.standard_normal(N_Z)
    measurement[2] = bad
    assert observer.update(measurement, np.zeros(N_U)) is False
    bad_input = np.array([0.0, bad])
    assert observer.update(rng.standard_normal(N_Z), bad_input) is False
    assert np.array_equal(observer.lifted_state_estimate, before_z)
    assert np.array_equal(observer.disturbance_estimate, before_w)
    state = observer.state
    assert eso_update(state, measurement, np.zeros(N_U), params) is state
    assert np.array_equal(innovated_disturbance(state, measurement, params), before_w)
    assert observer.update(rng.standard_normal(N_Z), np.zeros(N_U)) is True
    print(f"{bad} measurement rejected; estimate unchanged, next finite sample accepted")


def test_innovated_disturbance_equals_update_result() -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    params = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    rng = np.random.default_rng(8)
    state = EsoState(rng.standard_normal(N_Z), rng.standard_normal(N_Z))
    z = rng.standard_normal(N_Z)
    early = innovated_disturbance(state, z, params)
    late = eso_update(state, z, rng.standard_normal(N_U), params).disturbance_estimate
    assert np.max(np.abs(early - late)) < 1e-12


def test_pluggable_correction_functions() -> None:
    """A saturating g (a nonlinear ESO) is called and changes the update."""
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    calls = []

    def saturate(z_tilde: np.ndarray) -> np.ndarray:
        calls.append(z_tilde.shape)
        return np.clip(z_tilde, -0.1, 0.1)

    linear = EsoParams(A, B, offset, gains.beta1, gains.beta2)
    saturated = EsoParams(A, B, offset, gains.beta1, gains.beta2, g1=saturate, g2=saturate)
    state = initial_state(np.zeros(N_Z), linear)
    z = np.full(N_Z, 1.0)
    a = eso_update(state, z, np.zeros(N_U), linear)
    b = eso_update(state, z, np.zeros(N_U), saturated)
    assert calls == [(N_Z,), (N_Z,)]
    assert np.allclose(b.disturbance_estimate, -gains.beta2 @ np.full(N_Z, 0.1))
    assert not np.allclose(a.disturbance_estimate, b.disturbance_estimate)
    nan_state = eso_update(state, np.full(N_Z, np.nan), np.zeros(N_U), saturated)
    assert nan_state is state


def test_bad_shapes_raise_typed_errors() -> None:
    A, B, offset = linear_system()
    gains = design_gains(A, 0.6)
    with pytest.raises(EsoShapeError, match="A must be square"):
        EsoParams(A[:, :3], B, offset, -0.5, -0.1)
    with pytest.raises(EsoShapeError, match="B must be"):
        EsoParams(A, B[:3], offset, gains.beta1, gains.beta2)
    with pytest.raises(EsoShapeError, match="offset must be"):
        EsoParams(A, B, offset[:2], gains.beta1, gains.beta2)
    with pytest.raises(EsoShapeError, match="beta1 must be"):
        EsoParams(A, B, offset, np.eye(3), gains.beta2)
    with pytest.raises(EsoShapeError, match="non-finite"):
        EsoParams(A, B, offset * np.nan, gains.beta1, gains.beta2)
    with pytest.raises(EsoShapeError, match="callables"):
        EsoParams(A, B, offset, gains.beta1, gains.beta2, g1=None)  # type: ignore[arg-type]
    observer = ExtendedStateObserver(EsoParams(A, B, offset, gains.beta1, gains.beta2))
    with pytest.raises(EsoShapeError, match="update expects"):
        observer.update(np.zeros(N_Z + 1), np.zeros(N_U))
    with pytest.raises(EsoShapeError, match="initial lifted state"):
        observer.reset(np.full(N_Z, np.nan))


@pytest.mark.timing
def test_update_time_report() -> None:
    """Benchmark of the hot path (n_z = 8, as the d = 5 model): a report, generous bound."""
    rng = np.random.default_rng(0)
    n_z = 8
    A = np.eye(n_z) + 0.03 * rng.standard_normal((n_z, n_z))
    gains = design_gains(A, 0.6)
    params = EsoParams(A, rng.standard_normal((n_z, 2)), rng.standard_normal(n_z), gains.beta1, gains.beta2)
    state = initial_state(np.zeros(n_z), params)
    observer = ExtendedStateObserver(params)
    z, u = rng.standard_normal(n_z), rng.standard_normal(2)
    number = 5000
    pure = min(timeit.repeat(lambda: eso_update(state, z, u, params), number=number, repeat=3)) / number
    wrapped = min(timeit.repeat(lambda: observer.update(z, u), number=number, repeat=3)) / number
    print(f"eso_update {pure * 1e6:.1f} us, ExtendedStateObserver.update {wrapped * 1e6:.1f} us (n_z={n_z})")
    assert wrapped < 200e-6  # an order of magnitude above the 20 us target: catches regressions only

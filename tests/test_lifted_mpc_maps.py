"""The Koopman MPCs' per-speed set-up (``controller.lifted_mpc.PredictionMaps`` and ESO-DKMPC's
observer maps) against the plain formulas it was rewritten from for speed: the same bits on
every speed quantum of the committed artefacts, so the commands cannot move."""
from __future__ import annotations

import numpy as np
import pytest

from controller.lifted_mpc import VEHICLE_STATES, PredictionMaps, decayed_sums, held_input_basis
from controller.qp_mpc import held_input_map
from controller.registry import create_controller
from models.koopman import SPEED_QUANTUM


def einsum_basis(free_from_lifted: np.ndarray, hold: np.ndarray) -> np.ndarray:
    """G[i] = sum_j hold[j, c] F[i-1-j], one einsum per step: the original form, (Np + 1, n_x, Nc, n_z)."""
    n_steps, n_x, n_z = free_from_lifted.shape
    basis = np.zeros((n_steps, n_x, hold.shape[1], n_z))
    for i in range(1, n_steps):
        basis[i] = np.einsum("jc,jxz->xcz", hold[:i], free_from_lifted[i - 1::-1])
    return basis


def eye_per_step_sums(A: np.ndarray, n_pred: int, decay: float) -> np.ndarray:
    """D_i with a fresh identity per step: the original form, (Np + 1, n_z, n_z)."""
    sums = np.zeros((n_pred + 1, A.shape[0], A.shape[0]))
    for i in range(n_pred):
        sums[i + 1] = A @ sums[i] + decay ** i * np.eye(A.shape[0])
    return sums


@pytest.mark.parametrize("name", ["eso-dkmpc", "dmdc-eso"])
def test_maps_bit_identical_on_every_speed_quantum(name: str) -> None:
    controller = create_controller(name)
    model, hold = controller.model, controller.hold
    knots = model.speed_knots if model.form == "scheduled" else (10.0, 10.0)
    speeds = np.arange(round(knots[0] / SPEED_QUANTUM), round(knots[-1] / SPEED_QUANTUM) + 1) * SPEED_QUANTUM
    decay = controller._eso_tuning.disturbance_decay
    for speed in speeds:
        maps = controller.prediction_maps(float(speed))
        local = maps.model
        assert maps.gain_basis.tobytes() == einsum_basis(maps.free_from_lifted, hold).tobytes(), speed
        for d in (1.0, 0.93):
            assert decayed_sums(local.A, hold.shape[0], d).tobytes() == eye_per_step_sums(
                local.A, hold.shape[0], d).tobytes(), speed
        _, horizon_map = controller._observer_for(maps)
        expected = local.C_P[:len(VEHICLE_STATES)] @ eye_per_step_sums(local.A, hold.shape[0], decay)
        assert horizon_map.tobytes() == expected.tobytes(), speed


@pytest.mark.parametrize("n_pred, n_ctrl", [(30, 8), (5, 5), (4, 7), (1, 1), (6, 1)])
def test_held_input_basis_equals_einsum(n_pred: int, n_ctrl: int) -> None:
    rng = np.random.default_rng(n_pred * 10 + n_ctrl)
    free_from_lifted = rng.normal(size=(n_pred + 1, 3, 5))
    hold = held_input_map(n_pred, n_ctrl)
    assert held_input_basis(free_from_lifted, n_ctrl).tobytes() == einsum_basis(free_from_lifted, hold).tobytes()


def test_other_hold_map_keeps_the_general_form() -> None:
    """A hold map other than the held-input one still gets G = sum_j hold[j, c] F[i-1-j]."""
    controller = create_controller("dmdc-eso")
    hold = np.zeros((4, 2))
    hold[:, 0] = 0.5
    hold[2:, 1] = 1.0
    maps = PredictionMaps.build(controller.model, hold)
    assert np.array_equal(maps.gain_basis, einsum_basis(maps.free_from_lifted, hold))

"""ESO-DKMPC's observer: the disturbance over the horizon, and closed-loop stability on both
lane changes with the shipped tuning (the tuning itself: tests/test_tuning_sweep.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from controller.base import VehicleSample
from controller.dkmpc import Dkmpc
from controller.eso_dkmpc import EsoDkmpc
from controller.lifted_mpc import decayed_sums
from controller.tuning import load_tuning
from test_controller_doubles import koopman_double


def test_decayed_sums_match_their_definition() -> None:
    rng = np.random.default_rng(3)
    A = 0.3 * rng.normal(size=(4, 4))
    n_pred = 7
    powers = [np.linalg.matrix_power(A, k) for k in range(n_pred + 1)]
    for decay in (0.0, 0.6, 1.0):
        sums = decayed_sums(A, n_pred, decay)
        expected = [sum((powers[i - 1 - j] * decay ** j for j in range(i)), np.zeros((4, 4)))
                    for i in range(n_pred + 1)]
        assert sums.shape == (n_pred + 1, 4, 4)
        assert np.allclose(sums, expected, atol=1e-14)
    assert np.allclose(decayed_sums(A, n_pred, 0.0)[1:], powers[:n_pred])  # only w at step 0 counts


@pytest.mark.parametrize("decay", [1.0, 0.8])
def test_prediction_adds_the_disturbance_as_a_rollout_does(decay: float) -> None:
    """ESO-DKMPC's free response minus DKMPC's (same model) is the lifted rollout of
    x[i+1] = A x[i] + decay^i w from x[0] = 0, seen through C_P."""
    tuning = load_tuning()
    model = koopman_double(10.0)
    eso = EsoDkmpc(model, dataclasses.replace(tuning.eso_dkmpc, disturbance_decay=decay), tuning.longitudinal)
    dk = Dkmpc(model, tuning.dkmpc, tuning.longitudinal)
    w = np.array([0.01, -0.02, 0.005])[: model.n_z]
    eso.disturbance = lambda lifted: w  # a known estimate instead of the observer's
    sample = VehicleSample(10.0, 0.1, 0.02, 0.0, 0.0, 0.0, 100.0, 0.01, 10.0)
    free_eso, gain_eso = eso.predict_states(sample, 150.0)
    free_dk, gain_dk = dk.predict_states(sample, 150.0)
    x, expected = np.zeros(model.n_z), [np.zeros(model.n_z)]
    for i in range(tuning.eso_dkmpc.prediction_horizon):
        x = model.A @ x + decay ** i * w
        expected.append(x)
    expected = np.array(expected) @ model.C_P.T
    print(f"decay {decay}: disturbance share at the horizon end {free_eso[-1] - free_dk[-1]}")
    assert np.array_equal(gain_eso, gain_dk)
    assert np.allclose(free_eso - free_dk, expected, atol=1e-12)


def test_koopman_mpcs_complete_both_lane_changes_with_the_trained_artefact() -> None:
    """Stability with the shipped tuning and the trained artefact on the study's closed loop
    (``make tables`` runs the same): both Koopman MPCs complete the high-mu and the low-mu
    double lane change within 2 m. No ranking is asserted: which controller tracks better
    is a measured result of the study, not a property of the code."""
    from controller.registry import create_controller
    from studies.closed_loop import run_closed_loop
    from hil.scenario import load_scenario
    from models.koopman import DEFAULT_ARTIFACT

    if not DEFAULT_ARTIFACT.exists():
        pytest.skip("models/artifacts/dk_d5.npz not trained yet (make train)")
    for scenario_name in ("dlc_high_mu", "dlc_low_mu"):
        scenario = load_scenario(scenario_name)
        rmse = {}
        for name in ("dkmpc", "eso-dkmpc"):
            result = run_closed_loop(scenario, create_controller(name))
            assert result.completed, result.failure
            assert result.tracking.lateral.max_abs < 2.0
            rmse[name] = result.tracking.lateral.rmse
        print(f"{scenario_name}: e_Y RMSE ESO-DKMPC {rmse['eso-dkmpc']:.4f} m, DKMPC {rmse['dkmpc']:.4f} m")

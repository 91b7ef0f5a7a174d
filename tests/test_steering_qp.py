"""The steering QP's sparsity (controller/steering_qp.py): A holds only the causal entries
of the state gain, which every QP controller's prediction leaves zero elsewhere; the solution
equals the one of the same QP with the full dense gain block; and the soft rows are those of
SOFT_STATES at the first SOFT_LEADING_STEPS steps, every SOFT_STEP_STRIDE-th step and the last."""
from __future__ import annotations

import numpy as np
import osqp
import pytest
import scipy.sparse as sparse

from controller.base import VehicleSample
from controller.reference import ReferencePath
from controller.registry import MPC_NAMES, create_controller
from controller.steering_qp import (N_SOFT_STATES, OSQP_SCALING_ITERATIONS, SOFT_LEADING_STEPS, SOFT_STATES,
                                   SOFT_STEP_STRIDE, SteeringQp, soft_state_rows, soft_steps)
from controller.tuning import load_tuning

#: The controllers that solve SteeringQp (NMPC solves its own NLP; the geometric baselines none).
QP_CONTROLLERS = [name for name in MPC_NAMES if name != "nmpc"]


def koopman_artefact_missing() -> bool:
    from models.koopman import DEFAULT_ARTIFACT

    return not DEFAULT_ARTIFACT.exists()


def _non_causal(n_pred: int, n_ctrl: int) -> np.ndarray:
    """(Np, 3, Nc) mask of the gain entries A leaves out: state at step k + 1, input c > k."""
    steps, inputs = np.arange(n_pred)[:, None, None], np.arange(n_ctrl)[None, None, :]
    return np.broadcast_to(inputs > steps, (n_pred, N_SOFT_STATES, n_ctrl))


@pytest.mark.parametrize("name", QP_CONTROLLERS)
def test_every_qp_controller_predicts_zero_where_a_has_no_entry(name: str, monkeypatch) -> None:
    if name in ("eso-dkmpc", "dkmpc", "dmdc-eso") and koopman_artefact_missing():
        pytest.skip("models/artifacts/dk_d5.npz not trained yet (make train)")
    gains = []
    solve = SteeringQp.solve

    def recording(self, pose_jacobian, pose_offset, previous_steer, state_gain, *args, **kwargs):
        gains.append(np.array(state_gain))
        return solve(self, pose_jacobian, pose_offset, previous_steer, state_gain, *args, **kwargs)

    monkeypatch.setattr(SteeringQp, "solve", recording)
    controller = create_controller(name)
    controller.set_path(ReferencePath.double_lane_change())
    for vx, y in ((9.7, 0.3), (15.0, -0.2), (25.0, 0.1)):
        controller.step(VehicleSample(vx=vx, vy=0.1, yaw_rate=0.05, x=0.0, y=y, yaw=0.02, steer_angle=0.01,
                                      drive_torque=0.0, target_speed=vx))
    assert len(gains) == 3
    for gain in gains:
        mask = _non_causal(*gain.shape[::2])
        print(name, "gain", gain.shape, "entries left out of A:", int(mask.sum()),
              "largest |causal entry|", float(np.abs(gain[~mask]).max()))
        assert np.all(gain[mask] == 0.0)
        assert np.abs(gain[~mask]).max() > 0.0


def test_causal_pattern_solves_the_same_qp_as_the_dense_one() -> None:
    """SteeringQp against OSQP on the same QP with every gain entry in A (random data)."""
    tuning = load_tuning(None).for_controller("lmpc")
    n_pred, n_ctrl = tuning.prediction_horizon, tuning.control_horizon
    qp = SteeringQp(tuning)
    rng = np.random.default_rng(3)
    jac = rng.normal(scale=0.05, size=(n_pred, 3, n_ctrl))
    offset = rng.normal(scale=0.3, size=(n_pred, 3))
    gain = rng.normal(scale=0.5, size=(n_pred, 3, n_ctrl))
    gain[_non_causal(n_pred, n_ctrl)] = 0.0
    free = np.tile([10.0, 0.0, 0.0], (n_pred, 1)) + rng.normal(scale=0.5, size=(n_pred, 3))
    free[5:, 2] += 0.7  # the yaw-rate bound 0.8 rad/s is reached: constraints active
    solution = qp.solve(jac, offset, 0.01, gain, free, np.zeros(n_ctrl))

    # The dense reference: the same P, q, l, u; A with the whole gain block of the soft rows.
    soft = soft_state_rows(n_pred)
    rows = gain.reshape(-1, n_ctrl)[soft]
    weight = np.tile([tuning.q_position, tuning.q_position, tuning.q_yaw], n_pred)
    j = jac.reshape(-1, n_ctrl)
    difference = np.eye(n_ctrl) - np.eye(n_ctrl, k=-1)
    hessian = j.T @ (j * weight[:, None]) + tuning.r_steer * np.eye(n_ctrl) \
        + tuning.p_steer_rate * difference.T @ difference
    p = sparse.block_diag((2.0 * hessian, 2.0 * tuning.slack_l2 * np.eye(N_SOFT_STATES)), format="csc")
    q = np.concatenate((2.0 * (offset.ravel() * weight) @ j, np.full(N_SOFT_STATES, tuning.slack_l1)))
    q[0] -= 2.0 * tuning.p_steer_rate * 0.01
    slack = np.eye(N_SOFT_STATES)[soft % N_SOFT_STATES]  # each soft row's own state's slack
    a = sparse.csc_matrix(np.vstack((np.eye(n_ctrl + N_SOFT_STATES), np.hstack((rows, -slack)),
                                     np.hstack((rows, slack)))))
    state_min, state_max = np.tile(tuning.state_min, n_pred)[soft], np.tile(tuning.state_max, n_pred)[soft]
    lower = np.concatenate((np.full(n_ctrl, -0.3), np.zeros(N_SOFT_STATES), np.full(rows.shape[0], -np.inf),
                            state_min - free.ravel()[soft]))
    upper = np.concatenate((np.full(n_ctrl, 0.3), np.full(N_SOFT_STATES, np.inf), state_max - free.ravel()[soft],
                            np.full(rows.shape[0], np.inf)))
    dense = osqp.OSQP()
    dense.setup(sparse.triu(p, format="csc"), q, a, lower, upper, verbose=False, polishing=True,
                eps_abs=1e-9, eps_rel=1e-9, max_iter=100000, scaling=OSQP_SCALING_ITERATIONS)
    reference = dense.solve(raise_error=False)
    print("steer", solution.steer, "slack", solution.slack, "iterations", solution.iterations)
    print("dense reference steer", reference.x[:n_ctrl], "slack", reference.x[n_ctrl:])
    assert solution.status.name == "SOLVED" and reference.info.status == "solved"
    assert np.max(reference.x[n_ctrl:]) > 1e-3  # the soft constraint is active
    # SteeringQp stops at eps 1e-3: its answer within that of the tightly solved dense QP.
    assert np.allclose(solution.steer, reference.x[:n_ctrl], atol=5e-3)
    assert np.allclose(solution.slack, reference.x[n_ctrl:], atol=5e-3)


@pytest.mark.parametrize("n_pred", [1, 2, 3, 4, 29, 30, 31])
def test_soft_rows_at_the_first_step_every_stride_th_step_and_the_last(n_pred: int) -> None:
    steps = soft_steps(n_pred) + 1  # 1-based prediction steps
    leading = set(range(1, min(SOFT_LEADING_STEPS, n_pred) + 1))
    expected = sorted(leading | set(range(SOFT_STEP_STRIDE, n_pred + 1, SOFT_STEP_STRIDE)) | {n_pred})
    print(f"Np {n_pred}: soft steps {steps.tolist()}")
    assert steps.tolist() == expected
    # Step 1 is always checked: the first predicted states are the ones the next command moves most.
    assert SOFT_LEADING_STEPS >= 1 and steps[0] == 1
    rows = soft_state_rows(n_pred)
    assert rows.tolist() == [3 * (s - 1) + k for s in expected for k in SOFT_STATES]
    assert 0 not in SOFT_STATES  # no vx rows: the longitudinal controller owns vx


def test_qp_has_one_row_pair_per_soft_row_and_the_vx_slack_stays_zero() -> None:
    """The constraint count follows soft_state_rows; the vx slack, with no soft row, is 0
    even when vx is far outside its bounds (no vx rows to violate)."""
    tuning = load_tuning(None).for_controller("eso-dkmpc")
    n_pred, n_ctrl = tuning.prediction_horizon, tuning.control_horizon
    qp = SteeringQp(tuning)
    n_rows = soft_state_rows(n_pred).size
    assert qp._lower.size == n_ctrl + N_SOFT_STATES + 2 * n_rows
    free = np.tile([tuning.state_max[0] + 20.0, 0.0, 0.0], (n_pred, 1))  # vx 20 m/s above its bound
    solution = qp.solve(np.zeros((n_pred, 3, n_ctrl)), np.zeros((n_pred, 3)), 0.0, np.zeros((n_pred, 3, n_ctrl)),
                        free, np.zeros(n_ctrl))
    print("Np", n_pred, "soft state rows", n_rows, "constraints", qp._lower.size, "slack", solution.slack)
    assert solution.status.name == "SOLVED"
    assert abs(solution.slack[0]) < 1e-6

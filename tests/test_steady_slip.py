"""The heading target's steady side slip (controller/steady_slip.py): the steady-state map
against a direct solve, the reference's bend, the bound and the fade, and the MPC's heading
target moved by it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controller.steady_slip import reference_bend, slip_target, steady_slip_map
from models.bicycle import LinearBicycle


def _steady_vy(A: np.ndarray, B: np.ndarray, drift: np.ndarray, held: dict[int, float], vy_row: int = 1) -> float:
    """vy of the steady state x = A x + B u + drift with the states ``held`` (row -> value)
    fixed and the inputs free, by a direct least-squares solve of the stacked system."""
    n, m = B.shape
    rows = [np.hstack([np.eye(n) - A, -B])]
    rhs = [drift]
    for row, value in held.items():
        pick = np.zeros((1, n + m))
        pick[0, row] = 1.0
        rows.append(pick)
        rhs.append(np.array([value]))
    solution = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return float(solution[vy_row])


def test_the_map_gives_the_steady_vy_a_constant_disturbance_adds() -> None:
    rng = np.random.default_rng(3)
    n = 6
    A = 0.6 * np.eye(n) + 0.05 * rng.standard_normal((n, n))
    B = rng.standard_normal((n, 2))
    offset, w = rng.standard_normal(n), rng.standard_normal(n)
    slip_map = steady_slip_map(A, B, vy_row=1, yaw_rate_row=2, vx_row=0)
    held = {2: 0.0, 0: 7.5}  # a straight road at the present speed
    expected = _steady_vy(A, B, offset + w, held) - _steady_vy(A, B, offset, held)
    assert slip_map @ w == pytest.approx(expected, rel=1e-9)


def test_the_bicycle_crabs_into_a_side_force_and_a_singular_model_gives_no_slip() -> None:
    """The bicycle at 15 m/s pushed along +y by a constant w on vy: to hold a straight
    (no yaw rate) it must steer, and its steady vy is the model's answer, whatever its sign."""
    a, b = LinearBicycle().discrete_matrices(15.0, 0.025)
    a, b = np.asarray(a, float), np.asarray(b, float).reshape(2, 1)
    slip_map = steady_slip_map(a, b, vy_row=0, yaw_rate_row=1)
    w = np.array([0.01, 0.0])
    direct = np.linalg.solve(np.block([[np.eye(2) - a, -b], [np.array([[0.0, 1.0, 0.0]])]]),
                             np.array([0.01, 0.0, 0.0]))[0]
    assert slip_map @ w == pytest.approx(direct, rel=1e-9)
    assert slip_map @ w == pytest.approx(_steady_vy(a, b, w, {1: 0.0}, vy_row=0), rel=1e-9)
    assert abs(direct) > 1e-4
    # no steady state (the yaw rate cannot be held without an input): no slip
    assert np.array_equal(steady_slip_map(a, np.zeros((2, 1)), 0, 1), np.zeros(2))
    with pytest.raises(ValueError, match="held states"):
        steady_slip_map(a, np.zeros((2, 2)), 0, 1)


def test_the_bend_is_zero_on_a_straight_and_an_arc_and_grows_in_a_lane_change() -> None:
    steps = np.arange(30)
    assert reference_bend(np.full(30, 0.3)) == 0.0
    assert reference_bend(0.3 + 0.004 * steps) == pytest.approx(0.0, abs=1e-12)
    # an arc across the +-pi wrap is still an arc
    assert reference_bend(np.remainder(math.pi - 0.05 + 0.004 * steps + math.pi, 2 * math.pi) - math.pi) \
        == pytest.approx(0.0, abs=1e-9)
    lane_change = 0.05 * np.sin(np.pi * steps / 29)
    assert reference_bend(lane_change) == pytest.approx(0.05, rel=1e-2)


def test_the_target_is_bounded_faded_and_off_at_limit_zero() -> None:
    assert slip_target(0.005, 0.0, 0.02, 0.01) == 0.005
    assert slip_target(-0.05, 0.0, 0.02, 0.01) == -0.02
    assert slip_target(0.005, 0.005, 0.02, 0.01) == pytest.approx(0.0025)
    assert slip_target(0.005, 0.02, 0.02, 0.01) == 0.0
    assert slip_target(0.005, 0.0, 0.0, 0.01) == 0.0
    assert slip_target(math.nan, 0.0, 0.02, 0.01) == 0.0

"""Small stand-in models for the controller tests (and checks that they are sane).

``BicycleDouble`` is a linear 2-DoF bicycle written here, independent of models/;
``koopman_double`` wraps it (at one speed) as a KoopmanModel with lift = identity, so the
Koopman controllers can be tested on a plant that IS their model.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

TS = 0.025
MASS = 1648.0  # kg
YAW_INERTIA = 2600.0  # kg m^2
FRONT_LENGTH, REAR_LENGTH = 1.2, 1.5  # m
FRONT_STIFFNESS, REAR_STIFFNESS = 90000.0, 100000.0  # N/rad per axle
WHEEL_RADIUS = 0.32  # m


class BicycleDouble:
    """Linear 2-DoF bicycle, state [vy, yaw_rate], input steer (rad)."""

    def continuous_matrices(self, vx: float) -> tuple[np.ndarray, np.ndarray]:
        cf, cr, lf, lr = FRONT_STIFFNESS, REAR_STIFFNESS, FRONT_LENGTH, REAR_LENGTH
        a = np.array([
            [-(cf + cr) / (MASS * vx), -(lf * cf - lr * cr) / (MASS * vx) - vx],
            [-(lf * cf - lr * cr) / (YAW_INERTIA * vx), -(lf**2 * cf + lr**2 * cr) / (YAW_INERTIA * vx)],
        ])
        b = np.array([[cf / MASS], [lf * cf / YAW_INERTIA]])
        return a, b

    def discrete_matrices(self, vx: float, ts: float) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.continuous_matrices(vx)
        block = np.zeros((3, 3))
        block[:2, :2], block[:2, 2:] = a, b
        zoh = scipy.linalg.expm(block * ts)  # zero-order hold
        return zoh[:2, :2], zoh[:2, 2:]


def koopman_arrays(vx: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """A (3, 3), B (3, 2) of [vx, vy, yaw_rate] with inputs [torque, steer] at speed vx."""
    ad, bd = BicycleDouble().discrete_matrices(vx, TS)
    a = np.eye(3)
    a[1:, 1:] = ad
    b = np.zeros((3, 2))
    b[0, 0] = TS / (MASS * WHEEL_RADIUS)  # torque accelerates, nothing else acts on vx
    b[1:, 1] = bd[:, 0]
    return a, b


def koopman_double(vx: float = 10.0):
    """``models.koopman.KoopmanModel`` with no encoder (z = x): the linear double above."""
    from models.koopman import KoopmanModel

    a, b = koopman_arrays(vx)
    return KoopmanModel(a, b, None, [], TS, ("vx", "vy", "yaw_rate"), ("torque", "steer"))


def test_bicycle_double_is_stable_and_steers_left() -> None:
    ad, bd = BicycleDouble().discrete_matrices(10.0, TS)
    radius = max(abs(np.linalg.eigvals(ad)))
    state = np.zeros(2)
    for _ in range(200):
        state = ad @ state + bd[:, 0] * 0.02
    understeer_rate = state[1]
    print(f"spectral radius {radius:.4f}, steady yaw rate at 0.02 rad {understeer_rate:.4f} rad/s")
    assert radius < 1.0
    # Kinematic yaw rate vx * delta / L = 0.074; an understeering car stays below it.
    assert 0.03 < understeer_rate < 10.0 * 0.02 / (FRONT_LENGTH + REAR_LENGTH)


def bicycle_dynamics_casadi(state, steer, torque):
    """Continuous dynamics of the double for NMPC tests: (3,) derivatives of [vx, vy, yaw_rate]
    (vx from the torque only; lateral from the linear bicycle at the current vx)."""
    import casadi as ca

    vx, vy, yaw_rate = state[0], state[1], state[2]
    cf, cr, lf, lr = FRONT_STIFFNESS, REAR_STIFFNESS, FRONT_LENGTH, REAR_LENGTH
    vy_rate = (-(cf + cr) / (MASS * vx) * vy + (-(lf * cf - lr * cr) / (MASS * vx) - vx) * yaw_rate
               + cf / MASS * steer)
    yaw_acc = (-(lf * cf - lr * cr) / (YAW_INERTIA * vx) * vy
               - (lf**2 * cf + lr**2 * cr) / (YAW_INERTIA * vx) * yaw_rate + lf * cf / YAW_INERTIA * steer)
    return ca.vertcat(torque / (MASS * WHEEL_RADIUS), vy_rate, yaw_acc)

"""Linear 2-DoF bicycle model (LMPC baseline) and the nominal parameters of the baselines.

The baseline controllers get what an engineer would have: nominal mass, inertia,
geometry and tyre curves, not the plant's internal state (load transfer, combined slip,
wheel dynamics, actuator lags). ``nominal_model_params()`` builds them from
``models/vehicle.toml``.

Cornering stiffness identification (documented in docs/plant.md): for each
axle, the plant's own tyre function ``models.tyre.tyre_forces`` is evaluated at the static
wheel load, zero slip ratio and lateral slips tan(alpha) = +-1e-4 rad (far inside the
linear range); the central difference is the tyre's slope at zero slip, and the axle's
stiffness is twice that (two tyres). This is what a flat-track test at small slip would
measure; the plant's degressive load sensitivity is thereby taken at the static loads, and
the rear axle's tyres with their own ``cornering_stiffness_rear_scale`` (1.0 in
models/vehicle.toml, so the nominal bicycle is the same with or without that factor).

Linear bicycle (state [vy, yaw_rate], input front wheel angle delta, constant vx):

    m (dvy/dt + vx r) = Cf (delta - (vy + lf r)/vx) + Cr (-(vy - lr r)/vx)
    Iz dr/dt          = lf Cf (delta - (vy + lf r)/vx) - lr Cr (-(vy - lr r)/vx)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from models.errors import ModelError
from models.tyre import tyre_forces
from models.vehicle_params import VehicleParams, load_vehicle_params

#: Lateral slip (tan alpha) used for the central difference; MF is linear to 1e-8 here.
IDENTIFICATION_SLIP = 1e-4


class BicycleModelError(ModelError):
    """The linear bicycle was asked for a speed where it is not defined (vx <= 0)."""


@dataclass(frozen=True)
class NominalModelParams:
    """Nominal parameters for the baseline models (SI units).

    Cornering stiffnesses and Magic Formula peaks are per AXLE (two tyres).
    """

    mass: float
    yaw_inertia: float
    lf: float
    lr: float
    wheel_radius: float
    mu: float
    cornering_stiffness_front: float
    cornering_stiffness_rear: float
    mf_shape: float
    mf_curvature: float
    peak_force_front: float
    peak_force_rear: float
    drive_split_front: float
    drag_factor: float
    rolling_resistance_force: float
    steer_limit: float
    #: Speed (m/s) that regularises vx in slip angles: sqrt(vx^2 + v^2), smooth and finite.
    slip_speed_floor: float

    @property
    def wheelbase(self) -> float:
        """lf + lr (m)."""
        return self.lf + self.lr

    @property
    def mf_stiffness_front(self) -> float:
        """Magic Formula B of the front axle (1/rad): slope at zero slip = Cf."""
        return self.cornering_stiffness_front / (self.mf_shape * self.peak_force_front)

    @property
    def mf_stiffness_rear(self) -> float:
        """Magic Formula B of the rear axle (1/rad)."""
        return self.cornering_stiffness_rear / (self.mf_shape * self.peak_force_rear)

    @property
    def understeer_gradient(self) -> float:
        """K_us = m/L (lr/Cf - lf/Cr) in rad per m/s^2 (> 0: understeer)."""
        return self.mass / self.wheelbase * (self.lr / self.cornering_stiffness_front
                                             - self.lf / self.cornering_stiffness_rear)


def identify_axle_cornering_stiffness(axle_load: float, params: VehicleParams,
                                      stiffness_scale: float = 1.0) -> float:
    """Slope dFy/dalpha (N/rad) of one axle at zero slip, from the plant's tyre curve
    with the axle's factor ``stiffness_scale`` on the tyres' cornering stiffness."""
    wheel_load = np.array(axle_load / 2.0)
    eps = IDENTIFICATION_SLIP
    _, fy_plus = tyre_forces(np.array(0.0), np.array(eps), wheel_load, params.mu, params, stiffness_scale)
    _, fy_minus = tyre_forces(np.array(0.0), np.array(-eps), wheel_load, params.mu, params, stiffness_scale)
    return 2.0 * float(fy_plus - fy_minus) / (2.0 * eps)


def nominal_model_params(params: VehicleParams | None = None) -> NominalModelParams:
    """Nominal baseline parameters from the plant's parameter file (nominal mass and mu)."""
    p = params if params is not None else load_vehicle_params()
    front_load = p.mass * p.gravity * p.lr / p.wheelbase
    rear_load = p.mass * p.gravity * p.lf / p.wheelbase
    return NominalModelParams(
        mass=p.mass, yaw_inertia=p.yaw_inertia, lf=p.lf, lr=p.lr, wheel_radius=p.radius, mu=p.mu,
        cornering_stiffness_front=identify_axle_cornering_stiffness(front_load, p),
        cornering_stiffness_rear=identify_axle_cornering_stiffness(rear_load, p, p.cornering_stiffness_rear_scale),
        mf_shape=p.shape_lateral, mf_curvature=p.curvature_lateral,
        peak_force_front=p.mu * front_load, peak_force_rear=p.mu * rear_load,
        drive_split_front=p.drive_split_front,
        drag_factor=0.5 * p.air_density * p.drag_coefficient * p.frontal_area,
        rolling_resistance_force=p.rolling_resistance * p.mass * p.gravity,
        steer_limit=p.steer_limit, slip_speed_floor=p.slip_speed_floor)


class LinearBicycle:
    """Linear 2-DoF bicycle, state [vy, yaw_rate], input front wheel angle (rad)."""

    def __init__(self, params: NominalModelParams | None = None) -> None:
        self.params = params if params is not None else nominal_model_params()

    def continuous_matrices(self, vx: float) -> tuple[np.ndarray, np.ndarray]:
        """(A (2, 2), B (2, 1)) of dx/dt = A x + B delta at longitudinal speed ``vx`` > 0."""
        if not (math.isfinite(vx) and vx > 0.0):
            raise BicycleModelError(f"vx: the linear bicycle needs vx > 0, got {vx!r}")
        p = self.params
        cf, cr, m, iz = p.cornering_stiffness_front, p.cornering_stiffness_rear, p.mass, p.yaw_inertia
        a = np.array([
            [-(cf + cr) / (m * vx), -(p.lf * cf - p.lr * cr) / (m * vx) - vx],
            [-(p.lf * cf - p.lr * cr) / (iz * vx), -(p.lf ** 2 * cf + p.lr ** 2 * cr) / (iz * vx)],
        ])
        b = np.array([[cf / m], [p.lf * cf / iz]])
        return a, b

    def discrete_matrices(self, vx: float, ts: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact zero-order-hold discretisation (Ad (2, 2), Bd (2, 1)) for sample time ``ts``."""
        if not (math.isfinite(ts) and ts > 0.0):
            raise BicycleModelError(f"ts: must be > 0, got {ts!r}")
        a, b = self.continuous_matrices(vx)
        block = np.zeros((3, 3))
        block[:2, :2] = a
        block[:2, 2:] = b
        transition = scipy.linalg.expm(block * ts)
        return transition[:2, :2], transition[:2, 2:]

    def steady_state_yaw_rate_gain(self, vx: float) -> float:
        """r / delta in steady state: vx / (L + K_us vx^2) (1/s)."""
        p = self.params
        return vx / (p.wheelbase + p.understeer_gradient * vx ** 2)

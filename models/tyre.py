"""Magic Formula tyre: pure and combined slip, friction mu, load-dependent stiffness.

Pure slip (Pacejka, "Tyre and Vehicle Dynamics", MF with D = mu Fz):

    F = D sin(C atan(B s - E (B s - atan(B s))))

with B = K / (C D) so that the slope at zero slip is the stiffness K. Lateral stiffness
is load dependent (MF 5.2 form) K_a = p_ky1 Fz0 sin(2 atan(Fz / (p_ky2 Fz0))), which
makes an axle lose stiffness under lateral load transfer; longitudinal stiffness is
proportional to load, K_x = p_kx Fz. A per-tyre factor ``stiffness_scale`` multiplies K_a:
the plant gives the rear tyres ``cornering_stiffness_rear_scale`` (1.0 nominal; x * 1.0 is
exact, so the nominal car's forces are bit for bit those without the factor).

Combined slip uses the normalised slip vector rho = (B_x kappa, B_y tan(alpha)): each
direction gets D (rho_i / |rho|) times its own pure-slip curve evaluated at |rho|, so
pure slip is the exact MF and the resultant never exceeds about mu Fz (friction circle).

Sign convention: ``lateral_slip`` = tan(alpha) = -v_lateral / v_reference, so a positive
slip gives a positive (leftward in the wheel frame) force.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from models.vehicle_params import VehicleParams

#: Tiny offset that keeps |rho| and its derivative finite at zero slip.
_RHO_EPS2 = 1e-12


def mf_curve(rho: np.ndarray, shape: float, curvature: float,
             atan: Callable = np.arctan, sin: Callable = np.sin) -> np.ndarray:
    """Normalised pure-slip curve sin(C atan(rho - E (rho - atan rho))), rho = B * slip.

    ``atan`` and ``sin`` may be CasADi's so that the same curve is used symbolically.
    Shapes: any (element-wise).
    """
    return sin(shape * atan(rho - curvature * (rho - atan(rho))))


def cornering_stiffness(normal_load: np.ndarray, params: VehicleParams,
                        stiffness_scale: float | np.ndarray = 1.0) -> np.ndarray:
    """Cornering stiffness K_a (N/rad) of one tyre at ``normal_load`` (N), any shape,
    times ``stiffness_scale`` (broadcasts with the load: e.g. (4,) per wheel)."""
    fz0 = params.nominal_load
    return (params.cornering_stiffness_factor * fz0
            * np.sin(2.0 * np.arctan(normal_load / (params.cornering_stiffness_load_factor * fz0)))
            * stiffness_scale)


def wheel_stiffness_scale(params: VehicleParams, is_front: np.ndarray) -> np.ndarray:
    """Per-wheel factor on the cornering stiffness: 1 at the front wheels,
    ``cornering_stiffness_rear_scale`` at the rear; ``is_front`` (n,) of 1.0 / 0.0 -> (n,)."""
    return np.where(np.asarray(is_front) > 0.5, 1.0, params.cornering_stiffness_rear_scale)


def tyre_forces(slip_ratio: np.ndarray, lateral_slip: np.ndarray, normal_load: np.ndarray,
                mu: float | np.ndarray, params: VehicleParams,
                stiffness_scale: float | np.ndarray = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Combined-slip tyre forces in the wheel frame.

    Args: ``slip_ratio`` kappa, ``lateral_slip`` tan(alpha) (see module docstring),
    ``normal_load`` Fz > 0 (N), ``mu`` road friction, ``stiffness_scale`` the factor on
    each tyre's cornering stiffness (``wheel_stiffness_scale``); arrays broadcast together
    (e.g. (n_batch, 4) with a (4,) scale). Returns (Fx, Fy) in N with the broadcast shape.
    """
    peak = mu * normal_load
    b_long = params.slip_stiffness_factor / (params.shape_longitudinal * mu)
    b_lat = cornering_stiffness(normal_load, params, stiffness_scale) / (params.shape_lateral * peak)
    rho_x = b_long * slip_ratio
    rho_y = b_lat * lateral_slip
    rho = np.sqrt(rho_x * rho_x + rho_y * rho_y + _RHO_EPS2)
    fx = peak * (rho_x / rho) * mf_curve(rho, params.shape_longitudinal, params.curvature_longitudinal)
    fy = peak * (rho_y / rho) * mf_curve(rho, params.shape_lateral, params.curvature_lateral)
    return fx, fy

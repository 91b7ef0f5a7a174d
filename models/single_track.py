"""Nonlinear single-track model with Magic Formula lateral tyres (NMPC baseline).

``single_track_derivatives`` works on numpy arrays (state (..., 3)) and on CasADi
symbols (state an SX/MX 3-vector) through an ``ops`` namespace, so the NMPC can build its
IPOPT problem from the same equations. No hard branches: slip angles use the smooth
regularised speed sqrt(vx^2 + v_floor^2), the rolling resistance a tanh.

State [vx, vy, yaw_rate], inputs steer (front wheel angle, rad) and drive_torque (total,
N m, split front/rear with the nominal drive split, converted to force at the wheel
radius). Axle lateral forces (eq. 17 with nominal static loads, no load transfer):

    Fy = D sin(C atan(B a - E (B a - atan(B a)))),  D = mu Fz_axle, B = C_alpha / (C D)
    a_f = delta - atan((vy + lf r) / vx_reg),   a_r = -atan((vy - lr r) / vx_reg)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from models.bicycle import NominalModelParams, nominal_model_params
from models.tyre import mf_curve

__all__ = ["ModelOps", "NUMPY_OPS", "CASADI_OPS", "NominalModelParams", "nominal_model_params",
           "single_track_derivatives", "single_track_rk4_step"]

#: Width (m/s) of the tanh that fades rolling resistance through zero speed.
_ROLLING_FADE_SPEED = 0.2


@dataclass(frozen=True)
class ModelOps:
    """The math a model needs, from one library (numpy or CasADi)."""

    sin: Callable
    cos: Callable
    atan: Callable
    sqrt: Callable
    tanh: Callable
    #: Component i of a state: ``state[..., i]`` (numpy) or ``state[i]`` (CasADi).
    take: Callable[[Any, int], Any]
    #: Stack scalars/arrays into a state-shaped result.
    stack: Callable[[list], Any]


NUMPY_OPS = ModelOps(sin=np.sin, cos=np.cos, atan=np.arctan, sqrt=np.sqrt, tanh=np.tanh,
                     take=lambda state, i: state[..., i],
                     stack=lambda parts: np.stack(np.broadcast_arrays(*parts), axis=-1))


def _casadi_ops() -> ModelOps:
    import casadi

    return ModelOps(sin=casadi.sin, cos=casadi.cos, atan=casadi.atan, sqrt=casadi.sqrt,
                    tanh=casadi.tanh, take=lambda state, i: state[i],
                    stack=lambda parts: casadi.vertcat(*parts))


def __getattr__(name: str) -> Any:
    # CASADI_OPS is built on first use so that importing this module does not load casadi.
    if name == "CASADI_OPS":
        ops = _casadi_ops()
        globals()["CASADI_OPS"] = ops
        return ops
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def single_track_derivatives(state: Any, steer: Any, drive_torque: Any,
                             params: NominalModelParams, ops: ModelOps = NUMPY_OPS) -> Any:
    """d[vx, vy, yaw_rate]/dt.

    numpy: ``state`` (..., 3), ``steer`` and ``drive_torque`` broadcastable to (...,);
    returns (..., 3). CasADi (``ops=CASADI_OPS``): ``state`` a 3-vector symbol, returns a
    3-vector expression.
    """
    p = params
    vx, vy, yaw_rate = ops.take(state, 0), ops.take(state, 1), ops.take(state, 2)
    vx_reg = ops.sqrt(vx * vx + p.slip_speed_floor ** 2)
    alpha_front = steer - ops.atan((vy + p.lf * yaw_rate) / vx_reg)
    alpha_rear = -ops.atan((vy - p.lr * yaw_rate) / vx_reg)
    fy_front = p.peak_force_front * mf_curve(p.mf_stiffness_front * alpha_front, p.mf_shape,
                                             p.mf_curvature, atan=ops.atan, sin=ops.sin)
    fy_rear = p.peak_force_rear * mf_curve(p.mf_stiffness_rear * alpha_rear, p.mf_shape,
                                           p.mf_curvature, atan=ops.atan, sin=ops.sin)
    wheel_force = drive_torque / p.wheel_radius
    fx_front = p.drive_split_front * wheel_force
    fx_rear = (1.0 - p.drive_split_front) * wheel_force
    resistance = (p.drag_factor * vx * ops.sqrt(vx * vx + 1e-6)
                  + p.rolling_resistance_force * ops.tanh(vx / _ROLLING_FADE_SPEED))
    cos_d, sin_d = ops.cos(steer), ops.sin(steer)
    front_x = fx_front * cos_d - fy_front * sin_d
    front_y = fx_front * sin_d + fy_front * cos_d
    vx_dot = yaw_rate * vy + (front_x + fx_rear - resistance) / p.mass
    vy_dot = -yaw_rate * vx + (front_y + fy_rear) / p.mass
    yaw_acc = (p.lf * front_y - p.lr * fy_rear) / p.yaw_inertia
    return ops.stack([vx_dot, vy_dot, yaw_acc])


def single_track_rk4_step(state: Any, steer: Any, drive_torque: Any, params: NominalModelParams,
                          dt: float, ops: ModelOps = NUMPY_OPS) -> Any:
    """One RK4 step of ``dt`` with the inputs held (numpy or CasADi, as above)."""
    def f(x: Any) -> Any:
        return single_track_derivatives(x, steer, drive_torque, params, ops)
    k1 = f(state)
    k2 = f(state + 0.5 * dt * k1)
    k3 = f(state + 0.5 * dt * k2)
    k4 = f(state + dt * k3)
    return state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

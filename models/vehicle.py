"""Four-wheel planar vehicle plant (paper eqs. 16-17) with Magic Formula tyres.

Model (body frame at the CG, x forward, y left, yaw counter-clockwise):

- Newton-Euler planar motion of eq. 16 in continuous time, wheels 1 FL, 2 FR, 3 RL, 4 RR
  (the paper's numbering: 1 and 3 on the left, so their longitudinal forces give a
  negative yaw moment -w_B/2 F_x), plus aerodynamic drag and rolling resistance.
- Tyre forces (eq. 17) from ``models.tyre`` with combined slip, road friction ``mu`` and
  normal loads with static and dynamic (longitudinal and lateral) load transfer; the rear
  tyres' cornering stiffness times ``cornering_stiffness_rear_scale`` (1.0 nominal). The
  accelerations that drive the load transfer go through a first-order filter (suspension
  lag), which also removes the algebraic loop loads -> forces -> accelerations.
- Wheel spin dynamics J dw/dt = T_i - R F_x,i driven by in-wheel motor torques: the total
  torque T is split front/rear (separate drive and brake splits), equally left/right.
  Negative torque brakes: it opposes the wheel's rotation (fades below a small wheel
  speed) and never drives the car backwards.
- Steering actuator: rate-limited first-order lag on the front wheel angle, the command
  saturated at +-steer_limit; torque actuator: first-order lag, saturated.
- Disturbances (``models.disturbance``, optional): a steering offset between the actuator
  and the wheels, an external lateral force at the CG and yaw moment (crosswind, gusts,
  the bank's gravity component) and a factor on one tyre's cornering stiffness enter the
  derivative as a ``PlantDisturbance``; without one the equations are the nominal ones,
  evaluated by the same code (bit for bit the same results).

Why the wheel dynamics stay non-stiff: with the slip computed algebraically as
(wR - v)/v, the wheel mode has an eigenvalue ~ R^2 K_x / (J v), about 7000/v 1/s, which
RK4 at 1 ms cannot integrate below ~2.5 m/s. Here the slip ratio is a state with the
tyre's relaxation length sigma (Pacejka's transient slip model):

    sigma dkappa/dt = (w R - v_long) - v_ref kappa,   v_ref = sqrt(v_long^2 + v_floor^2)

whose steady state is the (regularised) slip ratio. Wheel and slip then form a
spring-mass pair with a speed-independent frequency sqrt(R^2 K_x / (J sigma)) ~ 130
rad/s, damped by v_ref/sigma and, at standstill, by a slip damping time t_d (the tyre
sees kappa + t_d dkappa/dt, Pacejka's low-speed damping, kept within mu Fz by the MF);
RK4 at 1 ms resolves it (h * lambda ~ 0.2; see tests/test_vehicle_stiffness.py).
Lateral slips use the same regularised denominator, and below ~2 m/s the lateral
states are blended to the kinematic bicycle, so standstill gives no NaN and no chatter.

Everything is vectorised over a leading batch dimension: ``VehicleBatch`` integrates
(n_batch, N_STATE) states at once (the data set generator), ``FourWheelVehicle`` is one
vehicle (the HIL plant node).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from models.errors import VehicleCommandError, VehicleDivergedError
from models.measurement import VehicleMeasurement, wrap_angle
from models.tyre import tyre_forces, wheel_stiffness_scale
from models.disturbance import Disturbances, DisturbanceSchedule, PlantDisturbance
from models.vehicle_params import VehicleParams, load_vehicle_params
from models.vehicle_params import WHEEL_NAMES  # noqa: F401  (the per-wheel order, FL FR RL RR)

# State layout of one vehicle (columns of the (n_batch, N_STATE) state array).
VX, VY, YAW_RATE, POS_X, POS_Y, YAW = 0, 1, 2, 3, 4, 5
WHEEL_SPEED = slice(6, 10)      # w_i (rad/s), wheels FL, FR, RL, RR
SLIP_RATIO = slice(10, 14)      # relaxed slip ratio kappa_i (-)
STEER = 14                       # actual front wheel angle (rad)
TORQUE = 15                      # actual total wheel torque (N m)
ACCEL_X_FILT, ACCEL_Y_FILT = 16, 17  # filtered body accelerations for load transfer (m/s^2)
N_STATE = 18

#: Width (m/s) of the tanh that fades rolling resistance through zero speed.
_ROLLING_FADE_SPEED = 0.2
#: Smallest normal load (N) a tyre is given (a lifted wheel keeps a tiny load, no 0/0).
_MIN_NORMAL_LOAD = 50.0


@dataclass(frozen=True)
class VehicleCommand:
    """Actuator command: total drive torque (N m, negative brakes), front wheel angle (rad)."""

    drive_torque: float
    steer_angle: float


#: What the plant reports: the CAN contract's eight measured signals (one shared type).
VehicleOutputs = VehicleMeasurement


@dataclass(frozen=True)
class VehicleDiagnostics:
    """Per-wheel quantities (arrays of shape (4,), order FL, FR, RL, RR), for diagnosis.

    Forces are in the wheel frame; ``slip_angle`` is alpha in rad (positive gives a
    leftward force); ``slip_ratio`` the relaxed kappa.
    """

    slip_ratio: np.ndarray
    slip_angle: np.ndarray
    longitudinal_force: np.ndarray
    lateral_force: np.ndarray
    normal_load: np.ndarray
    wheel_speed: np.ndarray


@dataclass(frozen=True)
class _WheelForces:
    """Intermediate per-wheel quantities of one derivative evaluation, (n_batch, 4) each."""

    slip_ratio: np.ndarray
    lateral_slip: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    fz: np.ndarray


class PlantModel:
    """Continuous-time plant derivative for a batch, with constants precomputed from params."""

    def __init__(self, params: VehicleParams) -> None:
        self.params = params
        p = params
        half_track = 0.5 * p.track
        self.wheel_x = np.array([p.lf, p.lf, -p.lr, -p.lr])
        self.wheel_y = np.array([half_track, -half_track, half_track, -half_track])
        self.is_front = np.array([1.0, 1.0, 0.0, 0.0])
        # Factor on each tyre's cornering stiffness: the rear axle's own (1.0 nominal).
        self.stiffness_scale = wheel_stiffness_scale(p, self.is_front)
        static_front = p.mass * p.gravity * p.lr / p.wheelbase / 2.0
        static_rear = p.mass * p.gravity * p.lf / p.wheelbase / 2.0
        self.static_load = np.array([static_front, static_front, static_rear, static_rear])
        # Load change per unit filtered acceleration: pitch (ax) and roll (ay) transfer.
        pitch = p.mass * p.cg_height / p.wheelbase / 2.0
        roll = p.mass * p.cg_height / p.track
        self.load_per_ax = np.array([-pitch, -pitch, pitch, pitch])
        self.load_per_ay = np.array([
            -roll * p.roll_stiffness_front, roll * p.roll_stiffness_front,
            -roll * (1.0 - p.roll_stiffness_front), roll * (1.0 - p.roll_stiffness_front)])
        self.drive_share = np.array([p.drive_split_front / 2, p.drive_split_front / 2,
                                     (1 - p.drive_split_front) / 2, (1 - p.drive_split_front) / 2])
        self.brake_share = np.array([p.brake_split_front / 2, p.brake_split_front / 2,
                                     (1 - p.brake_split_front) / 2, (1 - p.brake_split_front) / 2])
        self.drag_factor = 0.5 * p.air_density * p.drag_coefficient * p.frontal_area

    def initial_state(self, vx: np.ndarray) -> np.ndarray:
        """Straight rolling at speed ``vx`` (n_batch,), origin pose: (n_batch, N_STATE)."""
        vx = np.asarray(vx, dtype=float)
        state = np.zeros((vx.shape[0], N_STATE))
        state[:, VX] = vx
        state[:, WHEEL_SPEED] = vx[:, None] / self.params.radius
        return state

    def wheel_forces(self, state: np.ndarray, mu: np.ndarray, disturbance: PlantDisturbance | None = None,
                     ) -> tuple[_WheelForces, np.ndarray, np.ndarray, np.ndarray]:
        """Tyre quantities at ``state`` (n_batch, N_STATE) and friction ``mu`` (n_batch,),
        with ``disturbance``'s steering offset and stiffness factors (None: nominal).

        Returns (wheel forces, slip speed residual (n,4), cos of wheel angle (n,4),
        sin of wheel angle (n,4)).
        """
        p = self.params
        vx = state[:, VX:VX + 1]
        vy = state[:, VY:VY + 1]
        yaw_rate = state[:, YAW_RATE:YAW_RATE + 1]
        stiffness_scale = self.stiffness_scale
        if disturbance is None:
            wheel_angle = state[:, STEER:STEER + 1] * self.is_front
        else:
            wheel_angle = (state[:, STEER:STEER + 1] + disturbance.steer_offset_rad) * self.is_front
            stiffness_scale = stiffness_scale * np.array(disturbance.stiffness_scale)
        cos_w = np.cos(wheel_angle)
        sin_w = np.sin(wheel_angle)
        fz = (self.static_load + state[:, ACCEL_X_FILT:ACCEL_X_FILT + 1] * self.load_per_ax
              + state[:, ACCEL_Y_FILT:ACCEL_Y_FILT + 1] * self.load_per_ay)
        fz = np.maximum(fz, _MIN_NORMAL_LOAD)
        # Contact point velocities in the body frame, then in each wheel's frame.
        v_body_x = vx - self.wheel_y * yaw_rate
        v_body_y = vy + self.wheel_x * yaw_rate
        v_long = v_body_x * cos_w + v_body_y * sin_w
        v_lat = -v_body_x * sin_w + v_body_y * cos_w
        v_ref = np.sqrt(v_long * v_long + p.slip_speed_floor ** 2)
        lateral_slip = -v_lat / v_ref
        slip_ratio = state[:, SLIP_RATIO]
        residual = state[:, WHEEL_SPEED] * p.radius - v_long - v_ref * slip_ratio
        # The tyre sees the damped slip kappa + t_d dkappa/dt (dkappa/dt = residual/sigma);
        # the damping goes through the Magic Formula, so the force stays within mu Fz.
        damped_slip = slip_ratio + (p.slip_damping_time / p.relaxation_length) * residual
        fx, fy = tyre_forces(damped_slip, lateral_slip, fz, mu[:, None], p, stiffness_scale)
        return _WheelForces(slip_ratio, lateral_slip, fx, fy, fz), residual, cos_w, sin_w

    def derivatives(self, state: np.ndarray, steer_cmd: np.ndarray, torque_cmd: np.ndarray,
                    mu: np.ndarray, disturbance: PlantDisturbance | None = None) -> np.ndarray:
        """d(state)/dt, shape (n_batch, N_STATE).

        Args: ``state`` (n_batch, N_STATE); ``steer_cmd``, ``torque_cmd``, ``mu`` (n_batch,);
        ``disturbance``: what acts on every vehicle of the batch now (None: nothing). The
        external force and moment change the lateral and yaw accelerations; the load
        transfer follows the tyres' forces only (a force at the CG has no roll moment
        about it).
        """
        p = self.params
        forces, residual, cos_w, sin_w = self.wheel_forces(state, mu, disturbance)
        vx = state[:, VX]
        vy = state[:, VY]
        yaw_rate = state[:, YAW_RATE]
        yaw = state[:, YAW]
        steer = state[:, STEER]
        torque = state[:, TORQUE]

        fx_body = forces.fx * cos_w - forces.fy * sin_w
        fy_body = forces.fx * sin_w + forces.fy * cos_w
        force_x = fx_body.sum(axis=1)
        force_y = fy_body.sum(axis=1)
        yaw_moment = (self.wheel_x * fy_body - self.wheel_y * fx_body).sum(axis=1)
        resistance = (self.drag_factor * vx * np.abs(vx)
                      + p.rolling_resistance * p.mass * p.gravity * np.tanh(vx / _ROLLING_FADE_SPEED))
        accel_x = (force_x - resistance) / p.mass
        accel_y = force_y / p.mass

        deriv = np.empty_like(state)
        deriv[:, VX] = yaw_rate * vy + accel_x
        if disturbance is None:
            vy_dot = -yaw_rate * vx + accel_y
            yaw_acc = yaw_moment / p.yaw_inertia
            wheel_steer = steer
        else:
            vy_dot = -yaw_rate * vx + (force_y + disturbance.lateral_force_n) / p.mass
            yaw_acc = (yaw_moment + disturbance.yaw_moment_nm) / p.yaw_inertia
            wheel_steer = steer + disturbance.steer_offset_rad
        # Low-speed blend: below blend_speed_low the lateral states relax to the kinematic
        # bicycle (no slip), where the tyre model has no meaning; smoothstep in between.
        blend = np.clip((np.abs(vx) - p.blend_speed_low) / (p.blend_speed_high - p.blend_speed_low), 0.0, 1.0)
        blend = blend * blend * (3.0 - 2.0 * blend)
        yaw_rate_kin = vx * np.tan(wheel_steer) / p.wheelbase
        vy_kin = p.lr * yaw_rate_kin
        deriv[:, VY] = blend * vy_dot + (1.0 - blend) * (vy_kin - vy) / p.kinematic_time_constant
        deriv[:, YAW_RATE] = blend * yaw_acc + (1.0 - blend) * (yaw_rate_kin - yaw_rate) / p.kinematic_time_constant
        cos_yaw = np.cos(yaw)
        sin_yaw = np.sin(yaw)
        deriv[:, POS_X] = vx * cos_yaw - vy * sin_yaw
        deriv[:, POS_Y] = vx * sin_yaw + vy * cos_yaw
        deriv[:, YAW] = yaw_rate

        wheel_speed = state[:, WHEEL_SPEED]
        drive = np.maximum(torque, 0.0)[:, None] * self.drive_share
        brake = (np.minimum(torque, 0.0)[:, None] * self.brake_share
                 * np.tanh(wheel_speed / p.brake_fade_speed))
        deriv[:, WHEEL_SPEED] = (drive + brake - p.radius * forces.fx) / p.spin_inertia
        deriv[:, SLIP_RATIO] = residual / p.relaxation_length

        steer_target = np.clip(steer_cmd, -p.steer_limit, p.steer_limit)
        deriv[:, STEER] = np.clip((steer_target - steer) / p.steer_time_constant,
                                  -p.steer_rate_limit, p.steer_rate_limit)
        torque_target = np.clip(torque_cmd, -p.max_brake_torque, p.max_drive_torque)
        deriv[:, TORQUE] = (torque_target - torque) / p.torque_time_constant
        tau = p.load_transfer_time_constant
        deriv[:, ACCEL_X_FILT] = (accel_x - state[:, ACCEL_X_FILT]) / tau
        deriv[:, ACCEL_Y_FILT] = (accel_y - state[:, ACCEL_Y_FILT]) / tau
        return deriv

    def rk4_step(self, state: np.ndarray, steer_cmd: np.ndarray, torque_cmd: np.ndarray,
                 mu: np.ndarray, h: float, disturbance: PlantDisturbance | None = None) -> np.ndarray:
        """One classical RK4 step of size ``h`` with the commands and ``disturbance`` held;
        (n_batch, N_STATE)."""
        k1 = self.derivatives(state, steer_cmd, torque_cmd, mu, disturbance)
        k2 = self.derivatives(state + 0.5 * h * k1, steer_cmd, torque_cmd, mu, disturbance)
        k3 = self.derivatives(state + 0.5 * h * k2, steer_cmd, torque_cmd, mu, disturbance)
        k4 = self.derivatives(state + h * k3, steer_cmd, torque_cmd, mu, disturbance)
        return state + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


class ScalarPlant:
    """The same derivative as ``PlantModel.derivatives`` for ONE vehicle, on Python floats.

    numpy's per-call overhead dominates for a single vehicle (~20 small array operations
    per wheel quantity); plain floats with ``math`` are about 10x faster, which the HIL
    plant node needs (200 steps of 5 ms per simulated second). tests/test_vehicle_scalar.py
    checks it against the vectorised derivative to 1e-9.
    """

    def __init__(self, model: PlantModel) -> None:
        self.model = model
        p = model.params
        self.p = p
        self.wheels = tuple(zip(model.wheel_x.tolist(), model.wheel_y.tolist(), model.is_front.tolist(),
                                model.static_load.tolist(), model.load_per_ax.tolist(),
                                model.load_per_ay.tolist(), model.drive_share.tolist(),
                                model.brake_share.tolist(), model.stiffness_scale.tolist()))
        self.b_long_factor = p.slip_stiffness_factor / p.shape_longitudinal
        self.floor2 = p.slip_speed_floor ** 2
        self.damping_gain = p.slip_damping_time / p.relaxation_length
        self._scaled_wheels: dict[tuple[float, ...], tuple[tuple[float, ...], ...]] = {}

    def _wheels_for(self, disturbance: PlantDisturbance) -> tuple[tuple[float, ...], ...]:
        """``self.wheels`` with each stiffness factor times the disturbance's (cached)."""
        scale = disturbance.stiffness_scale
        wheels = self._scaled_wheels.get(scale)
        if wheels is None:
            wheels = tuple((*wheel[:-1], wheel[-1] * factor) for wheel, factor in zip(self.wheels, scale))
            self._scaled_wheels[scale] = wheels
        return wheels

    def derivatives(self, s: list[float], steer_cmd: float, torque_cmd: float, mu: float,
                    disturbance: PlantDisturbance | None = None) -> list[float]:
        """d(state)/dt for one state (list of N_STATE floats); same equations as the batch,
        ``disturbance`` included (None: nothing acts)."""
        p = self.p
        atan, sin, sqrt = math.atan, math.sin, math.sqrt
        vx, vy, yaw_rate, yaw = s[VX], s[VY], s[YAW_RATE], s[YAW]
        steer, torque = s[STEER], s[TORQUE]
        ax_f, ay_f = s[ACCEL_X_FILT], s[ACCEL_Y_FILT]
        wheels = self.wheels
        wheel_steer = steer
        if disturbance is not None:
            wheels = self._wheels_for(disturbance)
            wheel_steer = steer + disturbance.steer_offset_rad
        cos_s, sin_s = math.cos(wheel_steer), math.sin(wheel_steer)
        fz0 = p.nominal_load
        b_long = self.b_long_factor / mu
        c_long, e_long = p.shape_longitudinal, p.curvature_longitudinal
        c_lat, e_lat = p.shape_lateral, p.curvature_lateral
        force_x = force_y = yaw_moment = 0.0
        wheel_acc = [0.0] * 4
        slip_rate = [0.0] * 4
        drive = torque if torque > 0.0 else 0.0
        brake = torque if torque < 0.0 else 0.0
        for i, (wx, wy, front, static, per_ax, per_ay, drive_share, brake_share,
                stiffness_scale) in enumerate(wheels):
            cw, sw = (cos_s, sin_s) if front else (1.0, 0.0)
            fz = static + ax_f * per_ax + ay_f * per_ay
            if fz < _MIN_NORMAL_LOAD:
                fz = _MIN_NORMAL_LOAD
            vbx = vx - wy * yaw_rate
            vby = vy + wx * yaw_rate
            v_long = vbx * cw + vby * sw
            v_lat = -vbx * sw + vby * cw
            v_ref = sqrt(v_long * v_long + self.floor2)
            lateral_slip = -v_lat / v_ref
            kappa = s[10 + i]
            wheel_speed = s[6 + i]
            residual = wheel_speed * p.radius - v_long - v_ref * kappa
            damped = kappa + self.damping_gain * residual
            peak = mu * fz
            # models.tyre.cornering_stiffness, in the same order of operations.
            k_lat = (p.cornering_stiffness_factor * fz0 * sin(2.0 * atan(fz / (p.cornering_stiffness_load_factor * fz0)))
                     * stiffness_scale)
            rho_x = b_long * damped
            rho_y = k_lat / (c_lat * peak) * lateral_slip
            rho = sqrt(rho_x * rho_x + rho_y * rho_y + 1e-12)
            at = atan(rho)
            fx = peak * (rho_x / rho) * sin(c_long * atan(rho - e_long * (rho - at)))
            fy = peak * (rho_y / rho) * sin(c_lat * atan(rho - e_lat * (rho - at)))
            fxb = fx * cw - fy * sw
            fyb = fx * sw + fy * cw
            force_x += fxb
            force_y += fyb
            yaw_moment += wx * fyb - wy * fxb
            wheel_torque = drive * drive_share + brake * brake_share * math.tanh(wheel_speed / p.brake_fade_speed)
            wheel_acc[i] = (wheel_torque - p.radius * fx) / p.spin_inertia
            slip_rate[i] = residual / p.relaxation_length
        resistance = (self.model.drag_factor * vx * abs(vx)
                      + p.rolling_resistance * p.mass * p.gravity * math.tanh(vx / _ROLLING_FADE_SPEED))
        accel_x = (force_x - resistance) / p.mass
        accel_y = force_y / p.mass
        if disturbance is None:
            vy_dot = -yaw_rate * vx + accel_y
            yaw_acc = yaw_moment / p.yaw_inertia
        else:
            vy_dot = -yaw_rate * vx + (force_y + disturbance.lateral_force_n) / p.mass
            yaw_acc = (yaw_moment + disturbance.yaw_moment_nm) / p.yaw_inertia
        blend = (abs(vx) - p.blend_speed_low) / (p.blend_speed_high - p.blend_speed_low)
        blend = 0.0 if blend < 0.0 else (1.0 if blend > 1.0 else blend)
        blend = blend * blend * (3.0 - 2.0 * blend)
        yaw_rate_kin = vx * math.tan(wheel_steer) / p.wheelbase
        vy_kin = p.lr * yaw_rate_kin
        tau_k = p.kinematic_time_constant
        steer_target = min(max(steer_cmd, -p.steer_limit), p.steer_limit)
        steer_rate = min(max((steer_target - steer) / p.steer_time_constant, -p.steer_rate_limit), p.steer_rate_limit)
        torque_target = min(max(torque_cmd, -p.max_brake_torque), p.max_drive_torque)
        cos_y, sin_y = math.cos(yaw), math.sin(yaw)
        tau = p.load_transfer_time_constant
        return [
            yaw_rate * vy + accel_x,
            blend * vy_dot + (1.0 - blend) * (vy_kin - vy) / tau_k,
            blend * yaw_acc + (1.0 - blend) * (yaw_rate_kin - yaw_rate) / tau_k,
            vx * cos_y - vy * sin_y,
            vx * sin_y + vy * cos_y,
            yaw_rate,
            *wheel_acc,
            *slip_rate,
            steer_rate,
            (torque_target - torque) / p.torque_time_constant,
            (accel_x - ax_f) / tau,
            (accel_y - ay_f) / tau,
        ]

    def rk4_step(self, s: list[float], steer_cmd: float, torque_cmd: float, mu: float, h: float,
                 schedule: DisturbanceSchedule | None = None, time_s: float = 0.0) -> list[float]:
        """One RK4 step of ``h`` for one vehicle (lists of N_STATE floats), from ``time_s``;
        ``schedule`` gives the disturbance at each stage's time (None: nothing acts)."""
        f = self.derivatives
        if schedule is None:
            start = middle = end = None
        else:
            start, middle, end = schedule.stages(time_s, h)
        k1 = f(s, steer_cmd, torque_cmd, mu, start)
        k2 = f([x + 0.5 * h * k for x, k in zip(s, k1)], steer_cmd, torque_cmd, mu, middle)
        k3 = f([x + 0.5 * h * k for x, k in zip(s, k2)], steer_cmd, torque_cmd, mu, middle)
        k4 = f([x + h * k for x, k in zip(s, k3)], steer_cmd, torque_cmd, mu, end)
        h6 = h / 6.0
        return [x + h6 * (a + 2.0 * b + 2.0 * c + d) for x, a, b, c, d in zip(s, k1, k2, k3, k4)]


def substeps(dt: float, max_step: float) -> tuple[int, float]:
    """Number of RK4 steps and their size so that each is <= ``max_step``."""
    if not (math.isfinite(dt) and dt > 0.0):
        raise VehicleCommandError(f"dt: must be finite and > 0, got {dt!r}")
    count = max(1, math.ceil(dt / max_step - 1e-9))
    return count, dt / count


class VehicleBatch:
    """``n_batch`` independent plants integrated together (same params, own mu each)."""

    def __init__(self, params: VehicleParams, n_batch: int, mu: float | np.ndarray | None = None) -> None:
        self.model = PlantModel(params)
        self.params = params
        self.n_batch = int(n_batch)
        self.mu = np.broadcast_to(np.asarray(params.mu if mu is None else mu, dtype=float),
                                  (self.n_batch,)).copy()
        self.state = self.model.initial_state(np.zeros(self.n_batch))

    def reset(self, vx: np.ndarray) -> None:
        """Straight rolling at ``vx`` (n_batch,) from the origin."""
        self.state = self.model.initial_state(np.broadcast_to(vx, (self.n_batch,)))

    def step(self, steer_cmd: np.ndarray, torque_cmd: np.ndarray, dt: float) -> np.ndarray:
        """Advance by ``dt`` with commands (n_batch,) held; returns the new state."""
        count, h = substeps(dt, self.params.integration_step)
        steer_cmd = np.asarray(steer_cmd, dtype=float)
        torque_cmd = np.asarray(torque_cmd, dtype=float)
        state = self.state
        for _ in range(count):
            state = self.model.rk4_step(state, steer_cmd, torque_cmd, self.mu, h)
        self.state = state
        return state


class FourWheelVehicle:
    """One four-wheel plant: the HIL plant node's vehicle.

    ``params`` defaults to ``models/vehicle.toml``; ``mu`` and ``mass`` override the
    file's values (mass + 200 kg case: ``FourWheelVehicle(mass=1848.0)``).
    ``disturbances`` (``models.disturbance``) act from their ``start_s`` on the run's time
    ``time_s`` (0 at :meth:`reset`, advanced by :meth:`step`); :meth:`outputs` is what the
    sensors report (the yaw-rate bias on, the steering offset not seen),
    :meth:`true_outputs` the car's true motion.
    """

    def __init__(self, params: VehicleParams | None = None, *, mu: float | None = None,
                 mass: float | None = None, disturbances: Disturbances | None = None) -> None:
        params = params if params is not None else load_vehicle_params()
        if mass is not None:
            params = dataclasses.replace(params, mass=mass)
        if mu is not None:
            params = dataclasses.replace(params, mu=mu)
        self.params = params
        self.disturbances = disturbances if disturbances is not None else Disturbances()
        self._schedule = DisturbanceSchedule(disturbances, params) \
            if disturbances is not None and disturbances.any else None
        self.time_s = 0.0
        self._batch = VehicleBatch(params, 1)
        self._scalar = ScalarPlant(self._batch.model)
        self.reset()

    @property
    def mu(self) -> float:
        """Current road friction coefficient."""
        return float(self._batch.mu[0])

    def set_friction(self, mu: float) -> None:
        """Change the road friction from now on (mid-run mu step)."""
        if not (math.isfinite(mu) and 0.0 < mu <= 2.0):
            raise VehicleCommandError(f"mu: must be in (0, 2], got {mu!r}")
        self._batch.mu[0] = mu

    @property
    def state(self) -> np.ndarray:
        """Full internal state, shape (N_STATE,) (a copy)."""
        return self._batch.state[0].copy()

    def reset(self, vx: float = 0.0, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        """Straight rolling at ``vx`` at pose (x, y, yaw), actuators at rest, time 0."""
        self.time_s = 0.0
        self._batch.reset(np.array([vx], dtype=float))
        self._batch.state[0, POS_X] = x
        self._batch.state[0, POS_Y] = y
        self._batch.state[0, YAW] = yaw

    def step(self, command: VehicleCommand, dt: float) -> VehicleOutputs:
        """Hold ``command`` for ``dt`` seconds (RK4 at <= integration_step); new outputs."""
        if not (math.isfinite(command.steer_angle) and math.isfinite(command.drive_torque)):
            raise VehicleCommandError(f"command: must be finite, got {command!r}")
        count, h = substeps(dt, self.params.integration_step)
        state = self._batch.state[0].tolist()
        mu = float(self._batch.mu[0])
        if self._schedule is None:
            for _ in range(count):
                state = self._scalar.rk4_step(state, command.steer_angle, command.drive_torque, mu, h)
        else:
            for i in range(count):
                state = self._scalar.rk4_step(state, command.steer_angle, command.drive_torque, mu, h,
                                              self._schedule, self.time_s + i * h)
        if not all(math.isfinite(x) for x in state):
            raise VehicleDivergedError(f"plant state became non-finite: {state!r}")
        self._batch.state[0] = state
        # Rounded to 1 ns: the ticks' sum stays on the tick grid, so start_s lands on a tick.
        self.time_s = round(self.time_s + dt, 9)
        return self.outputs()

    def outputs(self) -> VehicleOutputs:
        """The signals of VEH_DYN / VEH_POSE_*, as the sensors report them: yaw wrapped to
        [-pi, pi), YAW_RATE with the disturbances' sensor bias, STEER_ANGLE the steering
        actuator's state (a disturbance's steering offset is not seen)."""
        s = self._batch.state[0]
        yaw_rate = float(s[YAW_RATE])
        if self._schedule is not None:
            yaw_rate += self.disturbances.yaw_rate_bias(self.time_s)
        return VehicleMeasurement(vx=float(s[VX]), vy=float(s[VY]), yaw_rate=yaw_rate,
                                  x=float(s[POS_X]), y=float(s[POS_Y]), yaw=wrap_angle(float(s[YAW])),
                                  steer_angle=float(s[STEER]), drive_torque=float(s[TORQUE]))

    def true_outputs(self) -> VehicleOutputs:
        """The car's true motion in the form of :meth:`outputs`: the true yaw rate and the
        true front wheel angle (actuator state + steering offset). Without disturbances
        the same as :meth:`outputs`."""
        out = self.outputs()
        if self._schedule is None:
            return out
        s = self._batch.state[0]
        return dataclasses.replace(out, yaw_rate=float(s[YAW_RATE]),
                                   steer_angle=float(s[STEER]) + self.disturbances.steer_offset(self.time_s))

    def diagnostics(self) -> VehicleDiagnostics:
        """Slips, forces and loads of the four wheels at the current state."""
        disturbance = None if self._schedule is None else self._schedule.at(self.time_s)
        forces, _, _, _ = self._batch.model.wheel_forces(self._batch.state, self._batch.mu, disturbance)
        return VehicleDiagnostics(
            slip_ratio=forces.slip_ratio[0].copy(),
            slip_angle=np.arctan(forces.lateral_slip[0]),
            longitudinal_force=forces.fx[0].copy(),
            lateral_force=forces.fy[0].copy(),
            normal_load=forces.fz[0].copy(),
            wheel_speed=self._batch.state[0, WHEEL_SPEED].copy())

"""The QP steering MPCs (LMPC, DKMPC, ESO-DKMPC) on plants that are their own models.

The plant here IS the linear double of test_controller_doubles (bicycle at 10 m/s), so
any steady tracking error would be the controller's fault, not a model mismatch.
"""
from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import osqp
import pytest

from controller.base import STEER_LIMIT_RAD, SolverStatus, VehicleSample
from controller.dkmpc import Dkmpc
from controller.eso_dkmpc import EsoDkmpc
from controller.lmpc import Lmpc
from controller.pose_kinematics import rollout_pose
from controller.reference import ReferencePath, lateral_error
from controller.steering_qp import soft_steps
from controller.tuning import load_tuning, with_fixed_weights
from models.measurement import wrap_angle
from test_controller_doubles import TS, BicycleDouble, koopman_arrays, koopman_double

SPEED = 10.0
NAMES = ("lmpc", "dkmpc", "eso-dkmpc")


def build(name: str, **overrides):
    """Controller ``name`` on the doubles, with tuning fields overridden (weights at every
    speed: a weight given replaces its low-speed twin too)."""
    tuning = load_tuning()
    table = with_fixed_weights(tuning.for_controller(name), **overrides)
    if name == "lmpc":
        return Lmpc(BicycleDouble(), table, tuning.longitudinal)
    if name == "dkmpc":
        return Dkmpc(koopman_double(SPEED), table, tuning.longitudinal)
    return EsoDkmpc(koopman_double(SPEED), table, tuning.longitudinal)


def straight(length: float = 400.0) -> ReferencePath:
    x = np.arange(-10.0, length, 0.25)
    return ReferencePath.from_arrays(x, np.zeros_like(x), np.zeros_like(x), "straight")


def circle(radius: float = 40.0) -> ReferencePath:
    angle = np.arange(0.0, 1.5 * math.pi, 0.2 / radius)
    return ReferencePath.from_arrays(radius * np.sin(angle), radius * (1 - np.cos(angle)), angle, "circle")


class LinearPlant:
    """[vx, vy, yaw_rate] by the Koopman double's A, B; pose by eq. 20; plus a constant
    lateral-velocity disturbance (m/s per step) the controllers' models do not know."""

    def __init__(self, pose: tuple[float, float, float], state=(SPEED, 0.0, 0.0), vy_disturbance: float = 0.0):
        self.a, self.b = koopman_arrays(SPEED)
        self.state = np.array(state, dtype=float)
        self.pose = np.array(pose, dtype=float)
        self.command = (0.0, 0.0)
        self.vy_disturbance = vy_disturbance

    def sample(self) -> VehicleSample:
        vx, vy, rate = self.state
        return VehicleSample(vx, vy, rate, self.pose[0], self.pose[1], float(wrap_angle(self.pose[2])),
                             self.command[0], self.command[1], SPEED)

    def apply(self, steer: float, torque: float) -> None:
        self.command = (steer, torque)
        self.pose = rollout_pose(self.pose, self.state[None, :], TS)[0]
        self.state = self.a @ self.state + self.b @ np.array([torque, steer])
        self.state[1] += self.vy_disturbance


def run(controller, path: ReferencePath, plant: LinearPlant, steps: int):
    """Closed loop; returns (lateral errors (steps,), commands, debugs)."""
    controller.set_path(path)
    errors, commands, debugs = [], [], []
    for _ in range(steps):
        command, debug = controller.step(plant.sample())
        plant.apply(command.steer_angle, command.drive_torque)
        errors.append(lateral_error(path, plant.pose[0], plant.pose[1]).lateral_error)
        commands.append(command)
        debugs.append(debug)
    return np.array(errors), commands, debugs


def pose_mismatch(sample: VehicleSample, debug, ts: float = TS, yaw_rate_bias: float = 0.0) -> tuple[float, float]:
    """Max |position| and |yaw| difference between the QP's predicted poses and eq. 20
    integrated with the QP's predicted states (the same inputs). ``yaw_rate_bias``: the
    observer's estimate of the yaw-rate sensor bias, which the QP's step 0 is corrected by."""
    states = np.vstack((sample.state() - np.array([0.0, 0.0, yaw_rate_bias]), debug.predicted_state[:-1]))
    rollout = rollout_pose(sample.pose(), states, ts)
    position = np.max(np.hypot(*(rollout[:, :2] - debug.predicted_pose[:, :2]).T))
    return float(position), float(np.max(np.abs(rollout[:, 2] - debug.predicted_pose[:, 2])))


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("shape", ["straight", "curve"])
def test_predicted_pose_matches_nonlinear_kinematics(name: str, shape: str) -> None:
    if shape == "straight":
        path, plant = straight(), LinearPlant((0.0, 0.8, 0.1))
    else:
        path, plant = circle(), LinearPlant((0.0, 0.0, 0.0), state=(SPEED, 0.0, SPEED / 40.0))
    controller = build(name)
    controller.set_path(path)
    worst_position, worst_yaw = 0.0, 0.0
    for k in range(80):
        sample = plant.sample()
        command, debug = controller.step(sample)
        assert debug.status == SolverStatus.SOLVED
        if k > 0:  # from the second step on the linearisation point is the shifted solution
            position, yaw = pose_mismatch(sample, debug, yaw_rate_bias=getattr(controller, "yaw_rate_bias", 0.0))
            worst_position, worst_yaw = max(worst_position, position), max(worst_yaw, yaw)
        plant.apply(command.steer_angle, command.drive_torque)
    print(f"{name} {shape}: max |QP pose - eq. 20 rollout| = {worst_position * 100:.2f} cm, "
          f"yaw {worst_yaw:.1e} rad over the {controller.tuning.prediction_horizon}-step horizon")
    assert worst_position < 0.02  # 2 cm over 0.75 s of prediction
    assert worst_yaw < 1e-9  # the yaw is linear in the steer: exact


@pytest.mark.parametrize("name", NAMES)
def test_straight_path_tracked_without_steady_error(name: str) -> None:
    errors, commands, debugs = run(build(name), straight(), LinearPlant((0.0, 1.0, 0.0)), 400)
    print(f"{name}: e_Y start {errors[0]:.3f} m, after 2.5 s {errors[100]:.4f} m, after 10 s {errors[-1]:.2e} m, "
          f"max overshoot {-errors.min():.4f} m")
    assert abs(errors[-1]) < 1e-3 and max(abs(errors[-40:])) < 1e-3
    assert not any(d.fallback for d in debugs)


@pytest.mark.parametrize("name", NAMES)
def test_steering_limit_holds_in_every_step(name: str) -> None:
    errors, commands, debugs = run(build(name, p_steer_rate=1.0), straight(), LinearPlant((0.0, 6.0, 0.0)), 200)
    steer = np.array([c.steer_angle for c in commands])
    print(f"{name}: 6 m offset, min steer {steer.min():.4f} rad, max {steer.max():.4f} rad, "
          f"e_Y after 5 s {errors[-1]:.3f} m")
    assert np.all(np.abs(steer) <= STEER_LIMIT_RAD)
    assert steer.min() == pytest.approx(-STEER_LIMIT_RAD, abs=1e-3)  # the limit was active
    assert abs(errors[-1]) < 0.1


@pytest.mark.parametrize("name", NAMES)
def test_state_constraint_violated_only_by_the_reported_slack(name: str) -> None:
    rate_limit = 0.1
    controller = build(name, state_min=(0.0, -2.0, -rate_limit), state_max=(40.0, 2.0, rate_limit))
    errors, commands, debugs = run(controller, straight(), LinearPlant((0.0, 4.0, 0.0)), 120)
    # ADMM meets constraints to its primal tolerance, about eps_abs + eps_rel * |row value|.
    tolerance = 2.0 * (controller.tuning.osqp_eps_abs + controller.tuning.osqp_eps_rel)
    # Eq. 21 is imposed at the QP's soft steps only (steering_qp.soft_steps: step 1, every
    # SOFT_STEP_STRIDE-th step, the last): checked there; the steps in between are reported.
    soft = soft_steps(controller.tuning.prediction_horizon)
    assert soft[0] == 0  # the first predicted step is among the checked ones
    worst_excess, worst_slack, worst_beyond, worst_between = 0.0, 0.0, -np.inf, -np.inf
    for debug in debugs:
        assert not debug.fallback
        rates = np.abs(debug.predicted_state[:, 2])
        excess = np.max(rates[soft]) - rate_limit
        assert excess <= debug.slack_max + tolerance, (excess, debug.slack_max)
        worst_beyond = max(worst_beyond, excess - debug.slack_max)
        worst_excess, worst_slack = max(worst_excess, excess), max(worst_slack, debug.slack_max)
        worst_between = max(worst_between, np.max(rates) - rate_limit - debug.slack_max)
    print(f"{name}: yaw-rate bound {rate_limit} rad/s, worst predicted excess at the soft steps {worst_excess:.4f}, "
          f"largest slack {worst_slack:.4f}, worst excess beyond the slack {worst_beyond:.1e} "
          f"(tolerance {tolerance:.0e}); at any step {worst_between:.4f} beyond the slack; "
          f"e_Y after 3 s {errors[-1]:.3f} m")
    assert worst_excess > -0.02  # the bound was (nearly) reached, so the test bites


@pytest.mark.parametrize("name", NAMES)
def test_forced_solver_failure_falls_back_within_limits(name: str, monkeypatch) -> None:
    controller = build(name)
    plant = LinearPlant((0.0, 1.0, 0.0))
    controller.set_path(straight())
    command, debug = controller.step(plant.sample())
    plan = controller._plan_steer.copy()
    plant.apply(command.steer_angle, command.drive_torque)
    failed = SimpleNamespace(x=np.full(controller.qp.n_ctrl + 3, np.nan), y=None,
                             info=SimpleNamespace(status_val=osqp.SolverStatus.OSQP_MAX_ITER_REACHED, iter=400, run_time=1e-3, obj_val=np.nan))
    monkeypatch.setattr(controller.qp._solver, "solve", lambda raise_error=False: failed)
    steers = []
    for k in range(controller.tuning.control_horizon + 3):
        command, debug = controller.step(plant.sample())
        plant.apply(command.steer_angle, command.drive_torque)
        assert debug.fallback and debug.status == SolverStatus.MAX_ITERATIONS
        assert abs(command.steer_angle) <= STEER_LIMIT_RAD and math.isfinite(command.drive_torque)
        steers.append(command.steer_angle)
    print(f"{name}: plan {np.round(plan, 4)}, fallback commands {np.round(steers, 4)}")
    n_ctrl = controller.tuning.control_horizon
    assert np.allclose(steers[:n_ctrl - 1], plan[1:])  # the shifted previous solution
    assert np.allclose(steers[n_ctrl - 1:], plan[-1])  # then the last command held


@pytest.mark.parametrize("name", NAMES)
def test_iteration_limit_gives_flagged_fallback(name: str) -> None:
    controller = build(name, osqp_max_iter=1)
    errors, commands, debugs = run(controller, straight(), LinearPlant((0.0, 2.0, 0.0)), 5)
    print(f"{name}: statuses {[d.status.name for d in debugs]}, steers {[c.steer_angle for c in commands]}")
    assert all(d.fallback and d.status == SolverStatus.MAX_ITERATIONS for d in debugs)
    assert all(c.steer_angle == 0.0 for c in commands)  # nothing to shift: hold the start value


@pytest.mark.parametrize("name", NAMES)
def test_non_finite_sample_is_not_run_and_never_raises(name: str) -> None:
    controller = build(name)
    plant = LinearPlant((0.0, 0.5, 0.0))
    controller.set_path(straight())
    good, _ = controller.step(plant.sample())
    for field in ("vx", "y", "yaw", "target_speed"):
        bad = dataclasses.replace(plant.sample(), **{field: math.nan})
        command, debug = controller.step(bad)
        print(field, command, debug.status.name, debug.fallback)
        assert debug.status == SolverStatus.NOT_RUN and debug.fallback
        assert abs(command.steer_angle) <= STEER_LIMIT_RAD and command.drive_torque == good.drive_torque
    command, debug = controller.step(plant.sample())
    assert debug.status == SolverStatus.SOLVED and not debug.fallback
    assert debug.observer_reset == (name == "eso-dkmpc")  # the observer restarts after the gap


def test_no_path_is_not_run() -> None:
    controller = build("dkmpc")
    command, debug = controller.step(LinearPlant((0.0, 0.0, 0.0)).sample())
    assert debug.status == SolverStatus.NOT_RUN and debug.fallback and command.steer_angle == 0.0


def test_eso_removes_the_steady_error_of_an_unmodelled_disturbance() -> None:
    """A constant lateral push the model does not know: DKMPC keeps an offset, ESO-DKMPC
    estimates the push in the lifted space and removes it (paper Section II-B)."""
    # The mechanism of eq. 15, not the tuned values: w_hat held over the horizon (a decaying
    # one under-predicts a constant push by design) and fixed weights and poles.
    weights = {"q_position": 10.0, "q_yaw": 20.0, "r_steer": 1.0, "p_steer_rate": 300.0}
    observer = {"eso_pole": 0.3, "eso_second_pole": 0.97, "disturbance_decay": 1.0}
    results = {}
    for name in ("dkmpc", "eso-dkmpc"):
        overrides = weights | (observer if name == "eso-dkmpc" else {})
        errors, _, debugs = run(build(name, **overrides), straight(),
                                LinearPlant((0.0, 0.0, 0.0), vy_disturbance=0.02), 400)
        results[name] = errors
        assert not any(d.fallback for d in debugs)
    steady = {name: float(np.mean(np.abs(e[-40:]))) for name, e in results.items()}
    print(f"steady |e_Y| with a 0.8 m/s^2 lateral push: DKMPC {steady['dkmpc']:.4f} m, "
          f"ESO-DKMPC {steady['eso-dkmpc']:.4f} m")
    assert steady["eso-dkmpc"] < 0.01 < steady["dkmpc"]


@pytest.mark.parametrize("name", NAMES)
def test_heading_west_across_the_yaw_wrap(name: str) -> None:
    """Driving along -x the measured yaw flips between +pi and -pi; nothing may notice."""
    x = np.arange(0.0, -300.0, -0.25)
    west = ReferencePath.from_arrays(x, np.zeros_like(x), np.full_like(x, math.pi), "west")
    plant = LinearPlant((0.0, -0.5, math.pi - 0.05))
    # Weights fixed here (not the tuned ones of tuning.toml): with them the approach
    # overshoots the path heading, so the measured yaw does cross the +-pi wrap.
    weights = {"q_position": 10.0, "q_yaw": 20.0, "r_steer": 1.0, "p_steer_rate": 300.0}
    errors, commands, debugs = run(build(name, **weights), west, plant, 200)
    wrapped_yaws = [d for d in debugs if d.predicted_pose.size and d.predicted_pose[0, 2] < 0]
    print(f"{name}: e_Y start {errors[0]:.3f} m, after 5 s {errors[-1]:.1e} m, steps seen with yaw < 0: "
          f"{len(wrapped_yaws)}, max |steer| {max(abs(c.steer_angle) for c in commands):.3f} rad")
    assert not any(d.fallback for d in debugs)
    assert abs(errors[-1]) < 1e-3 and len(wrapped_yaws) > 0


@pytest.mark.parametrize("advance", [0.0, 0.5])
def test_pose_jacobian_matches_finite_differences(advance: float) -> None:
    """With eq. 20's step (advance 0) and the midpoint heading (0.5)."""
    from controller.pose_kinematics import linearise_pose

    rng = np.random.default_rng(1)
    n, n_u = 30, 8
    states = np.column_stack((10 + 0.1 * rng.normal(size=n), 0.2 * rng.normal(size=n), 0.3 * rng.normal(size=n)))
    gain = 0.01 * rng.normal(size=(n, 3, n_u))
    pose0 = np.array([1.0, 2.0, 3.0])
    poses, jacobian = linearise_pose(pose0, states, gain, TS, advance)
    step = 1e-6
    finite = np.stack([(rollout_pose(pose0, states + gain @ d, TS, advance)
                        - rollout_pose(pose0, states - gain @ d, TS, advance)) / (2 * step)
                       for d in np.eye(n_u) * step], axis=2)
    error = np.max(np.abs(jacobian - finite))
    print(f"max |Jacobian - central differences| = {error:.1e} (entries up to {np.max(np.abs(jacobian)):.3f})")
    assert np.array_equal(poses, rollout_pose(pose0, states, TS, advance)) and error < 1e-7
    if advance == 0.0:  # eq. 20 itself: the same bits as without the argument
        assert np.array_equal(jacobian, linearise_pose(pose0, states, gain, TS)[1])


def test_horizon_pose_midpoint_stays_on_an_arc() -> None:
    """Constant speed and yaw rate (the straight-curve path's arc: R 50 m at 50 km/h): with
    the midpoint heading the predicted positions lie on the circle to a few micrometres
    after 1 s; eq. 20's explicit Euler (advance 0) runs outside it by about r ts / 2 times
    the distance (3.5 mrad: centimetres), which is why the option exists."""
    speed, yaw_rate, n = 13.9, 0.278, 40
    t = TS * np.arange(1, n + 1)
    exact = np.column_stack((np.sin(yaw_rate * t), 1.0 - np.cos(yaw_rate * t))) * speed / yaw_rate
    states = np.tile([speed, 0.0, yaw_rate], (n, 1))
    errors = {}
    for advance in (0.0, 0.5):
        poses = rollout_pose(np.zeros(3), states, TS, advance)
        errors[advance] = float(np.max(np.hypot(*(poses[:, :2] - exact).T)))
        assert np.allclose(poses[:, 2], yaw_rate * t)
    print(f"largest distance from the arc over {n} steps: Euler {errors[0.0] * 1e3:.2f} mm, "
          f"midpoint {errors[0.5] * 1e3:.4f} mm")
    assert errors[0.5] < 1e-4 and errors[0.0] > 0.01


@pytest.mark.parametrize("name", ["dkmpc", "eso-dkmpc"])
def test_predicted_pose_matches_with_the_trained_koopman_model(name: str) -> None:
    """The same kinematics check with the real lifted model (nonlinear lift, n_z > 3)."""
    from models.koopman import DEFAULT_ARTIFACT, KoopmanModel

    if not DEFAULT_ARTIFACT.exists():
        pytest.skip("models/artifacts/dk_d5.npz not trained yet (make train)")
    tuning = load_tuning()
    model = KoopmanModel.load()
    controller = (Dkmpc(model, tuning.dkmpc, tuning.longitudinal) if name == "dkmpc"
                  else EsoDkmpc(model, tuning.eso_dkmpc, tuning.longitudinal))
    plant = LinearPlant((0.0, 0.0, 0.0), state=(SPEED, 0.0, SPEED / 40.0))
    controller.set_path(circle())
    worst = 0.0
    for k in range(60):
        sample = plant.sample()
        command, debug = controller.step(sample)
        assert not debug.fallback
        if k > 0:
            worst = max(worst, pose_mismatch(sample, debug)[0])
        plant.apply(command.steer_angle, command.drive_torque)
    print(f"{name} (n_z = {model.n_z}) on a 40 m circle: max |QP pose - eq. 20 rollout| = {worst * 100:.2f} cm")
    assert worst < 0.02

"""The Koopman MPCs on the scheduled form and on a model with the measured wheel angle in its
state: the prediction they use equals the model's, and a closed loop on the doubles converges."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from controller.dkmpc import Dkmpc
from controller.errors import ControllerError
from controller.eso_dkmpc import EsoDkmpc
from controller.tuning import load_tuning
from models.koopman import KoopmanModel
from test_controller_doubles import TS, koopman_arrays
from test_controller_qp import LinearPlant, run, straight

SPEEDS = (5.0, 10.0, 20.0)
WHEEL = ("vx", "vy", "yaw_rate", "steer_measured")


def scheduled_double() -> KoopmanModel:
    """The bicycle double at three speed knots: a scheduled model that is exact at each knot."""
    arrays = [koopman_arrays(v) for v in SPEEDS]
    return KoopmanModel(np.stack([a for a, _ in arrays]), np.stack([b for _, b in arrays]), np.zeros((3, 3)), [],
                        TS, ("vx", "vy", "yaw_rate"), ("torque", "steer"), speed_knots=SPEEDS)


def wheel_angle_double(lag: float = 0.5) -> KoopmanModel:
    """The double with the wheel angle as a 4th state: it follows the command with a first-order
    lag (pole ``lag`` per step) and steers the car (B's steer column moves to A's 4th column)."""
    a3, b3 = koopman_arrays(10.0)
    a = np.zeros((4, 4))
    a[:3, :3] = a3
    a[:3, 3] = b3[:, 1]
    a[3, 3] = lag
    b = np.zeros((4, 2))
    b[0, 0] = b3[0, 0]
    b[3, 1] = 1.0 - lag
    return KoopmanModel(a, b, None, [], TS, WHEEL, ("torque", "steer"))


def build(cls, model: KoopmanModel, name: str):
    tuning = load_tuning()
    return cls(model, tuning.for_controller(name), tuning.longitudinal)


def test_scheduled_maps_are_those_of_the_measured_speed() -> None:
    model = scheduled_double()
    controller = build(Dkmpc, model, "dkmpc")
    for speed in (5.0, 7.5, 10.0, 20.0):
        maps = controller.prediction_maps(speed)
        expected_a, _, _ = model.matrices_for(np.array(speed))
        assert np.allclose(maps.model.A, expected_a, atol=1e-12)
        assert maps is controller.prediction_maps(speed)  # cached


@pytest.mark.parametrize("cls,name", [(Dkmpc, "dkmpc"), (EsoDkmpc, "eso-dkmpc")])
def test_scheduled_model_tracks_a_straight_path(cls, name: str) -> None:
    errors, commands, debugs = run(build(cls, scheduled_double(), name), straight(), LinearPlant((0.0, 0.5, 0.05)), 300)
    print(f"{name}: final |e_Y| {abs(errors[-1]):.4f} m")
    assert not any(d.fallback for d in debugs)
    assert abs(errors[-1]) < 0.05 and all(abs(c.steer_angle) <= 0.3 for c in commands)


def test_the_wheel_angle_state_is_lifted_from_the_measured_steer() -> None:
    controller = build(EsoDkmpc, wheel_angle_double(), "eso-dkmpc")
    plant = LinearPlant((0.0, 0.2, 0.0))
    controller.set_path(straight())
    sample = dataclasses.replace(plant.sample(), steer_angle=0.0123)
    command, debug = controller.step(sample)
    assert controller.lifted_state[3] == pytest.approx(0.0123)
    assert debug.predicted_state.shape == (controller.tuning.prediction_horizon, 3)
    assert abs(command.steer_angle) <= 0.3


def test_a_model_state_the_ecu_cannot_measure_is_refused() -> None:
    model = KoopmanModel(np.eye(4), np.zeros((4, 2)), None, [], TS, ("vx", "vy", "yaw_rate", "roll"),
                         ("torque", "steer"))
    with pytest.raises(ControllerError, match="roll|measured"):
        build(Dkmpc, model, "dkmpc")


def scheduled_bilinear_double(scale: float = 1.0) -> KoopmanModel:
    """The scheduled double with a steer-bilinear term: the yaw row's steer gain grows with the
    yaw rate (N[steer][2, 2] = ``scale``, per knot)."""
    arrays = [koopman_arrays(v) for v in SPEEDS]
    n = np.zeros((len(SPEEDS), 2, 3, 3))
    n[:, 1, 2, 2] = scale * np.array([1.0, 2.0, 3.0])
    return KoopmanModel(np.stack([a for a, _ in arrays]), np.stack([b for _, b in arrays]), np.zeros((3, 3)), [],
                        TS, ("vx", "vy", "yaw_rate"), ("torque", "steer"), speed_knots=SPEEDS, bilinear=n)


@pytest.mark.parametrize("cls,name", [(Dkmpc, "dkmpc"), (EsoDkmpc, "eso-dkmpc")])
def test_a_scheduled_bilinear_model_holds_b_of_the_measured_state(cls, name: str) -> None:
    """The steer gain the QP sees is that of B(z_k) = B(v) + N(v) z_k of the measured state."""
    model = scheduled_bilinear_double()
    controller = build(cls, model, name)
    controller.set_path(straight())
    sample = dataclasses.replace(LinearPlant((0.0, 0.2, 0.1)).sample(), vx=7.5, yaw_rate=0.2)
    _, gain = controller.predict_states(sample, 0.0)
    maps = controller.prediction_maps(7.5)
    z = controller.lifted_state
    expected_b = model.B_knots[0] * 0.5 + model.B_knots[1] * 0.5 + (model.bilinear_for(np.array(7.5)) @ z).T
    assert np.allclose(gain, maps.gain_basis @ expected_b[:, 1], atol=1e-12)
    assert not np.allclose(gain, maps.gain, atol=1e-6)  # the held B(z_k) is not B(v)


@pytest.mark.parametrize("cls,name", [(Dkmpc, "dkmpc"), (EsoDkmpc, "eso-dkmpc")])
def test_a_scheduled_bilinear_model_tracks_a_straight_path(cls, name: str) -> None:
    errors, commands, debugs = run(build(cls, scheduled_bilinear_double(0.2), name), straight(),
                                   LinearPlant((0.0, 0.5, 0.05)), 300)
    print(f"{name}: final |e_Y| {abs(errors[-1]):.4f} m")
    assert not any(d.fallback for d in debugs)
    assert abs(errors[-1]) < 0.05 and all(abs(c.steer_angle) <= 0.3 for c in commands)

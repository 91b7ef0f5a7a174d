"""The mirror-symmetric deep Koopman form: equivariance, no drift, servo lag, export, options."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.koopman import KoopmanError, KoopmanModel, MinMaxScaling, knot_weights  # noqa: E402
from models.koopman_metrics import Trajectory  # noqa: E402
from models.koopman_train import TrainingSettings, settings_json, train  # noqa: E402
from models.koopman_train_symmetric import (MirrorKoopmanNet, parities,  # noqa: E402
                                            shared_servo_scaling)
from test_koopman_synthetic import synthetic_runs  # noqa: E402

STATES = ("vx", "vy", "yaw_rate", "steer_measured")
INPUTS = ("torque", "steer")
KNOTS = (3.0, 10.0, 20.0, 35.0)
MIRROR_X = np.array([1.0, -1.0, -1.0, -1.0])
MIRROR_U = np.array([1.0, -1.0])


def _scalings() -> tuple[MinMaxScaling, MinMaxScaling]:
    """Deliberately lopsided bounds: the image of 0 is not the middle of the range."""
    states = MinMaxScaling(np.array([0.0, -2.0, -1.0, -0.3]), np.array([40.0, 3.0, 0.5, 0.4]))
    inputs = MinMaxScaling(np.array([-500.0, -0.25]), np.array([1500.0, 0.35]))
    return shared_servo_scaling(states, inputs, STATES, INPUTS)


def _random_net(servo: bool = True, seed: int = 0, bilinear: bool = False) -> MirrorKoopmanNet:
    """An untrained net with random (not identity) dynamics, so every check has something to
    catch; ``bilinear``: with a random steer-bilinear term."""
    torch.manual_seed(seed)
    states, inputs = _scalings()
    net = MirrorKoopmanNet(4, 2, 6, (16, 16), len(KNOTS), 2, parities(STATES), np.zeros(0), parities(INPUTS),
                           states.shift, np.zeros(0), inputs.shift, (), (3, 1) if servo else None,
                           1 if bilinear else None)
    with torch.no_grad():
        net.A_knots.add_(0.05 * torch.randn_like(net.A_knots))
        net.B_knots.add_(0.1 * torch.randn_like(net.B_knots))
        net.c_knots.add_(0.05 * torch.randn_like(net.c_knots))
        if bilinear:
            net.N_knots.add_(0.3 * torch.randn_like(net.N_knots))
    return net


def _model(net: MirrorKoopmanNet) -> KoopmanModel:
    states, inputs = _scalings()
    return KoopmanModel.from_normalised(net.export(states, inputs, (), None, KNOTS), 0.025, STATES, INPUTS)


def _starts(n: int = 8, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x0 = np.c_[rng.uniform(5, 30, n), rng.normal(0, 0.5, n), rng.normal(0, 0.2, n), rng.normal(0, 0.05, n)]
    u = np.stack([np.c_[rng.uniform(0, 800, 30), rng.normal(0, 0.05, 30)] for _ in range(n)])
    return x0, u


@pytest.mark.parametrize("bilinear", [False, True])
def test_the_exported_model_is_mirror_equivariant(bilinear: bool) -> None:
    """Mirrored start and inputs give the mirrored prediction, to rounding, in physical units."""
    model = _model(_random_net(bilinear=bilinear))
    assert model.scheduled_bilinear == bilinear
    x0, u = _starts()
    straight = model.predict(x0, u)
    mirrored = model.predict(x0 * MIRROR_X, u * MIRROR_U)
    print(f"largest equivariance error {np.abs(straight * MIRROR_X - mirrored).max():.1e}")
    assert np.abs(straight * MIRROR_X - mirrored).max() < 1e-9
    assert np.abs(straight[..., 1:]).max() > 1e-2  # not trivially zero: the model does turn


@pytest.mark.parametrize("bilinear", [False, True])
def test_straight_driving_with_the_wheels_straight_does_not_turn(bilinear: bool) -> None:
    model = _model(_random_net(bilinear=bilinear))
    inputs = np.zeros((1, 80, 2))
    inputs[..., 0] = 300.0
    predicted = model.predict(np.array([[15.0, 0.0, 0.0, 0.0]]), inputs)
    assert np.abs(predicted[0, :, 1:]).max() < 1e-10
    assert abs(predicted[0, -1, 0] - 15.0) > 1e-3  # the speed is free to change


@pytest.mark.parametrize("bilinear", [False, True])
def test_the_servo_lag_has_unit_dc_gain_in_physical_units(bilinear: bool) -> None:
    model = _model(_random_net(bilinear=bilinear))
    inputs = np.zeros((1, 400, 2))
    inputs[..., 1] = 0.02
    predicted = model.predict(np.array([[15.0, 0.0, 0.0, 0.0]]), inputs)
    assert predicted[0, -1, 3] == pytest.approx(0.02, abs=1e-9)
    assert predicted[0, 0, 3] < 0.02 * 0.9  # a lag, not a pass-through


def test_without_the_servo_the_wheel_angle_row_is_learned() -> None:
    model = _model(_random_net(servo=False))
    inputs = np.zeros((1, 400, 2))
    inputs[..., 1] = 0.02
    assert abs(model.predict(np.array([[15.0, 0.0, 0.0, 0.0]]), inputs)[0, -1, 3] - 0.02) > 1e-4


@pytest.mark.parametrize("bilinear", [False, True])
def test_torch_rollout_agrees_with_the_exported_numpy_model(bilinear: bool) -> None:
    net = _random_net(bilinear=bilinear)
    model = _model(net)
    states, inputs = _scalings()
    x0, u = _starts()
    net64 = net.double()
    weights = torch.as_tensor(knot_weights(np.array(KNOTS), x0[:, 0]))
    z0 = net64.lift(torch.as_tensor(states.normalise(x0)), torch.zeros(len(x0), 0, dtype=torch.float64))
    with torch.no_grad():
        rolled = net64.rollout(z0, torch.as_tensor(inputs.normalise(u)), weights)[..., :4].numpy()
    physical = rolled * (states.high - states.low) + states.low
    assert np.abs(physical - model.predict(x0, u)).max() < 1e-6


def test_per_step_schedule_moves_only_the_lateral_rows() -> None:
    """Scheduling the odd rows on each step's speed leaves the even (longitudinal) rows exactly
    as the held rollout has them: odd coordinates never feed even rows."""
    net = _random_net().double()
    states, inputs = _scalings()
    x0, u = _starts()
    held = torch.as_tensor(knot_weights(np.array(KNOTS), x0[:, 0]))
    stepping = torch.as_tensor(knot_weights(np.array(KNOTS), x0[:, :1] + np.linspace(0, 8, 30)[None]))
    z0 = net.lift(torch.as_tensor(states.normalise(x0)), torch.zeros(len(x0), 0, dtype=torch.float64))
    u_n = torch.as_tensor(inputs.normalise(u))
    with torch.no_grad():
        a = net.rollout(z0, u_n, held).numpy()
        b = net.rollout(z0, u_n, held, stepping).numpy()
        same = net.rollout(z0, u_n, held, held[:, None].expand(-1, 30, -1)).numpy()
    even = net.odd_rows.numpy() == 0
    assert np.abs(a[..., even] - b[..., even]).max() < 1e-12
    assert np.abs(a[..., ~even] - b[..., ~even]).max() > 1e-4
    assert np.abs(a - same).max() < 1e-12


def _steer_gain(model: KoopmanModel, start: np.ndarray) -> float:
    """Antisymmetric yaw-rate response after 0.5 s to a 0.01 rad steer change from ``start``,
    (n_x,), the steer otherwise held at the start's wheel angle and the torque at 300 N m."""
    inputs = np.zeros((2, 20, 2))
    inputs[..., 0] = 300.0
    inputs[..., 1] = start[3] + np.array([0.01, -0.01])[:, None]
    predicted = model.predict(np.stack([start, start]), inputs)
    return float(predicted[0, -1, 2] - predicted[1, -1, 2]) / 2


def test_the_steer_bilinear_term_makes_the_steer_response_depend_on_the_state() -> None:
    """At one speed, the linear-in-z form responds to a steer change alike from straight driving
    and from a corner; with the bilinear term it does not. Both keep the mirror: a left corner
    and a right one give the same gain."""
    straight, corner = np.array([15.0, 0.0, 0.0, 0.0]), np.array([15.0, 0.6, 0.3, 0.05])
    mirrored = corner * MIRROR_X
    plain, bilinear = _model(_random_net()), _model(_random_net(bilinear=True))
    assert _steer_gain(plain, corner) == pytest.approx(_steer_gain(plain, straight), rel=1e-9)
    gains = [_steer_gain(bilinear, start) for start in (straight, corner, mirrored)]
    print(f"bilinear steer gain: straight {gains[0]:.5f}, corner {gains[1]:.5f}, mirrored corner {gains[2]:.5f}")
    assert abs(gains[1] / gains[0] - 1) > 0.01
    assert gains[2] == pytest.approx(gains[1], rel=1e-9)


def test_the_scheduled_bilinear_artefact_round_trips(tmp_path) -> None:
    """Saved and loaded, it predicts the same; at_speed gives the bilinear model of that speed."""
    from models.koopman import save_artifact
    net = _random_net(bilinear=True)
    states, inputs = _scalings()
    learned = net.export(states, inputs, (), None, KNOTS)
    model = KoopmanModel.from_normalised(learned, 0.025, STATES, INPUTS, {"ts": 0.025})
    save_artifact(tmp_path / "m", learned, {"ts": 0.025, "state_names": list(STATES), "input_names": list(INPUTS)})
    loaded = KoopmanModel.load(tmp_path / "m")
    x0, u = _starts()
    assert loaded.scheduled_bilinear and loaded.form == "scheduled"
    assert np.abs(loaded.predict(x0, u) - model.predict(x0, u)).max() < 1e-12
    local = loaded.at_speed(12.0)
    assert local.form == "bilinear"
    start = np.array([[12.0, 0.3, 0.1, 0.02]])
    assert np.abs(local.predict(start, u[:1]) - loaded.predict(start, u[:1])).max() < 1e-9
    z = loaded.lift(start[0])
    assert np.allclose(local.input_matrix(z), local.B + (loaded.bilinear_for(np.array(12.0)) @ z).T)


def test_the_c_core_data_carries_the_steer_bilinear_term() -> None:
    """The C core's data file holds the steer's N(v) per knot (record koopman.N, physical
    units) under the scheduled bilinear form's code; a nonzero torque slice N[:, 0] is
    refused (the C core implements the steer's term only)."""
    import dataclasses

    from firmware.tools.ecu_data import SCHEDULED_BILINEAR, EcuDataError, model_records
    states, inputs = _scalings()
    learned = _random_net(bilinear=True).export(states, inputs, (), None, KNOTS)
    model = KoopmanModel.from_normalised(learned, 0.025, STATES, INPUTS)
    records = model_records(model)
    assert records["koopman.form"][0] == SCHEDULED_BILINEAR
    assert records["koopman.N"].shape == (len(KNOTS), model.n_z, model.n_z)
    assert np.array_equal(records["koopman.N"], model.N_knots[:, 1]) and np.abs(records["koopman.N"]).max() > 0
    assert not np.any(model.N_knots[:, 0])
    assert "koopman.N" not in model_records(_model(_random_net()))
    with_torque = np.array(learned.N_n, copy=True)
    with_torque[:, 0] = 0.01 * np.random.default_rng(0).standard_normal(with_torque[:, 0].shape)
    torque_model = KoopmanModel.from_normalised(dataclasses.replace(learned, N_n=with_torque), 0.025, STATES, INPUTS)
    with pytest.raises(EcuDataError, match=r"bilinear term N\(v\) of torque is not zero"):
        model_records(torque_model)


def _runs_with_wheel_angle() -> list[Trajectory]:
    """Synthetic runs with the wheel angle: a 0.1 s lag of the steer command."""
    runs = []
    for run in synthetic_runs(n_runs=5, n_samples=160, seed=3):
        wheel = np.zeros(len(run))
        for k in range(1, len(run)):
            wheel[k] = 0.78 * wheel[k - 1] + 0.22 * run.inputs[k - 1, 1]
        runs.append(Trajectory(run.name, np.c_[run.states, wheel], run.inputs, STATES, INPUTS))
    return runs


def test_training_the_mirror_form_gives_an_equivariant_artefact(tmp_path) -> None:
    settings = TrainingSettings(n_features=4, hidden=(16, 16), seq_len=6, batch_size=32, max_epochs=2,
                                steps_per_epoch=15, patience=2, val_windows=256, mirror_symmetric=True,
                                even_features=1, servo_lag=True, lateral_per_step=True)
    result = train(_runs_with_wheel_angle(), 0.025, settings, progress=False)
    model = result.model
    assert model.form == "scheduled" and model.n_features == 4
    assert [w.shape[0] for w, _ in model._layers] == [32, 32, 4]  # two passes, one MLP of twice the width
    x0, u = _starts()
    assert np.abs(model.predict(x0, u) * MIRROR_X - model.predict(x0 * MIRROR_X, u * MIRROR_U)).max() < 1e-9
    recorded = model.metadata["settings"]
    assert recorded["mirror_symmetric"] and recorded["servo_lag"] and recorded["lateral_per_step"]
    assert recorded["even_features"] == 1
    assert "steer_bilinear" not in recorded


def test_training_the_steer_bilinear_form_gives_an_equivariant_artefact() -> None:
    settings = TrainingSettings(n_features=4, hidden=(16, 16), seq_len=6, batch_size=32, max_epochs=2,
                                steps_per_epoch=15, patience=2, val_windows=256, mirror_symmetric=True,
                                even_features=1, servo_lag=True, steer_bilinear=True)
    result = train(_runs_with_wheel_angle(), 0.025, settings, progress=False)
    model = result.model
    assert model.scheduled_bilinear and model.metadata["settings"]["steer_bilinear"]
    assert np.abs(model.N_knots[:, 0]).max() == 0  # the torque has no bilinear term
    assert np.abs(model.N_knots[:, 1]).max() > 0  # trained away from its zero start
    x0, u = _starts()
    assert np.abs(model.predict(x0, u) * MIRROR_X - model.predict(x0 * MIRROR_X, u * MIRROR_U)).max() < 1e-9


def test_mirror_options_are_recorded_only_when_on() -> None:
    off = settings_json(TrainingSettings())
    assert not {"mirror_symmetric", "even_features", "servo_lag", "lateral_per_step", "steer_bilinear"} & set(off)


def test_bad_mirror_options_are_refused() -> None:
    with pytest.raises(KoopmanError, match="mirror_symmetric"):
        TrainingSettings(form="linear", mirror_symmetric=True)
    with pytest.raises(KoopmanError, match="servo_lag"):
        TrainingSettings(servo_lag=True)
    with pytest.raises(KoopmanError, match="lateral_per_step"):
        TrainingSettings(lateral_per_step=True)
    with pytest.raises(KoopmanError, match="steer_bilinear"):
        TrainingSettings(steer_bilinear=True)
    with pytest.raises(KoopmanError, match="even_features=6"):
        TrainingSettings(mirror_symmetric=True, n_features=5, even_features=6)
    with pytest.raises(KoopmanError, match=r"no parity known for \['roll_rate'\]"):
        parities(("vx", "roll_rate"))
    with pytest.raises(KoopmanError, match="servo_lag needs 'steer_measured' among the states"):
        states, inputs = _scalings()
        shared_servo_scaling(MinMaxScaling(states.low[:3], states.high[:3]), inputs, STATES[:3], INPUTS)


def test_servo_lag_without_a_wheel_angle_state_names_it() -> None:
    settings = TrainingSettings(n_features=2, hidden=(8,), seq_len=6, batch_size=8, max_epochs=1,
                                steps_per_epoch=2, mirror_symmetric=True, servo_lag=True)
    with pytest.raises(KoopmanError, match="steer_measured"):
        train(synthetic_runs(n_runs=4, n_samples=60, seed=1), 0.025, settings, progress=False)

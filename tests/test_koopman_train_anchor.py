"""The gain anchor: targets from local fits of the training runs, and the loss term."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.koopman import KoopmanError, KoopmanModel  # noqa: E402
from models.koopman_train_anchor import (ANCHOR_STEP, ANCHOR_STEPS, ANCHOR_SPEEDS, GainAnchor,  # noqa: E402
                                        anchor_targets, single_track_gain_fit)
from models.koopman_metrics import Trajectory  # noqa: E402
from models.koopman_train import TrainingSettings, settings_json  # noqa: E402
from test_koopman_symmetric import INPUTS, KNOTS, STATES, _random_net, _scalings  # noqa: E402


def _lateral_step(x: np.ndarray, steer: float, speed: float) -> np.ndarray:
    """A known linear lateral system [vy, r, delta] whose yaw gain grows with speed."""
    vy, r, delta = x
    return np.array([0.95 * vy - 0.004 * speed * delta, 0.9 * r + 0.004 * speed * delta + 0.001 * vy,
                     0.8 * delta + 0.2 * steer])


def _runs(offset: float = 0.0, lateral_step=_lateral_step) -> list[Trajectory]:
    """One run per anchor speed at constant speed of the car ``lateral_step`` (default this
    module's), the steer ``offset`` plus a small random signal."""
    rng = np.random.default_rng(4)
    runs = []
    for speed in ANCHOR_SPEEDS:
        steer = offset + 0.002 * np.sin(np.cumsum(rng.uniform(0.05, 0.3, 400)))
        x, states = np.zeros(3), []
        for k in range(400):
            states.append([speed, *x])
            x = lateral_step(x, steer[k], speed)
        runs.append(Trajectory(f"v{speed:g}", np.array(states), np.c_[np.full(400, 100.0), steer], STATES, INPUTS))
    return runs


def _true_response(speed: float) -> float:
    x = np.zeros(3)
    for _ in range(ANCHOR_STEPS):
        x = _lateral_step(x, ANCHOR_STEP, speed)
    return float(x[1])


def test_targets_are_the_local_fits_step_response_smoothed_over_speed() -> None:
    targets = anchor_targets(_runs())
    truth = np.array([_true_response(v) for v in targets.speeds])
    assert targets.speeds.tolist() == list(ANCHOR_SPEEDS)
    assert np.allclose(targets.fitted_yaw_rates, truth, rtol=1e-5)  # noise-free data: the fit is exact
    assert np.allclose(targets.yaw_rates, truth, rtol=0.02)  # the single-track smoothing through them
    assert np.all(targets.torques == 100.0) and np.all(targets.samples == 399)
    length, understeer = targets.single_track  # the targets are the single track's curve, at any speed
    assert targets.yaw_rates == pytest.approx(ANCHOR_STEP * targets.speeds / (length + understeer * targets.speeds ** 2),
                                              rel=1e-12)
    assert targets.yaw_rate_at(17.0) == pytest.approx(ANCHOR_STEP * 17.0 / (length + understeer * 17.0 ** 2), rel=1e-12)


def test_hard_driving_is_not_a_target() -> None:
    """Steering so hard that the combined acceleration leaves the gentle range everywhere
    leaves no speed to anchor on: a clear error, not a target from the limit."""
    with pytest.raises(KoopmanError, match="gentle samples"):
        anchor_targets(_runs(offset=1.0))


def test_the_loss_is_the_relative_error_of_the_exported_models_step_response() -> None:
    """The torch loss equals the same quantity computed on the exported numpy model."""
    targets = anchor_targets(_runs())
    states, inputs = _scalings()
    net = _random_net(bilinear=True).double()
    anchor = GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS)
    with torch.no_grad():
        loss = float(anchor.loss(net.float()))
    model = KoopmanModel.from_normalised(net.double().export(states, inputs, (), None, KNOTS), 0.025, STATES, INPUTS)
    commands = np.zeros((2, ANCHOR_STEPS, 2))
    commands[..., 0] = 100.0
    errors = []
    for speed, target in zip(targets.speeds, targets.yaw_rates):
        commands[0, :, 1], commands[1, :, 1] = ANCHOR_STEP, -ANCHOR_STEP
        final = model.predict(np.tile([speed, 0.0, 0.0, 0.0], (2, 1)), commands)[:, -1, 2]
        errors.append(((final[0] - final[1]) / 2 - target) / target)
    print(f"anchor loss {loss:.6f}, numpy {np.mean(np.square(errors)):.6f}")
    assert loss == pytest.approx(float(np.mean(np.square(errors))), rel=1e-3)
    assert loss > 1e-4  # a random net is off: the check has something to compare


def test_with_a_dictionary_the_loss_is_still_the_exported_models_step_response() -> None:
    """The starts' dictionary features enter the lift as in training: the torch loss equals
    the exported model's (whose lift computes the dictionary itself) with vx^2/100 in it."""
    from models.koopman_data import dictionary_scaling_of
    from models.koopman_train_symmetric import MirrorKoopmanNet, parities

    runs = _runs()
    targets = anchor_targets(runs)
    states, inputs = _scalings()
    dictionary = ("vy/vx", "vx^2/100")
    scaling = dictionary_scaling_of(runs, dictionary)
    torch.manual_seed(1)
    net = MirrorKoopmanNet(4, 2, 6, (16, 16), len(KNOTS), 2, parities(STATES), parities(dictionary), parities(INPUTS),
                           states.shift, scaling.shift, inputs.shift, (), (3, 1), 1)
    with torch.no_grad():
        net.A_knots.add_(0.05 * torch.randn_like(net.A_knots))
        net.B_knots.add_(0.1 * torch.randn_like(net.B_knots))
        net.N_knots.add_(0.3 * torch.randn_like(net.N_knots))
    anchor = GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS,
                        dictionary=dictionary, dictionary_scaling=scaling)
    without = GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS)
    with torch.no_grad():
        loss = float(anchor.loss(net))
        with pytest.raises(RuntimeError):  # the lift needs the features: no silent zeros
            without.loss(net)
    model = KoopmanModel.from_normalised(net.double().export(states, inputs, dictionary, scaling, KNOTS), 0.025,
                                         STATES, INPUTS)
    commands = np.zeros((2, ANCHOR_STEPS, 2))
    commands[..., 0] = 100.0
    commands[0, :, 1], commands[1, :, 1] = ANCHOR_STEP, -ANCHOR_STEP
    errors = []
    for speed, target in zip(targets.speeds, targets.yaw_rates):
        final = model.predict(np.tile([speed, 0.0, 0.0, 0.0], (2, 1)), commands)[:, -1, 2]
        errors.append(((final[0] - final[1]) / 2 - target) / target)
    print(f"anchor loss with a dictionary {loss:.6f}, numpy {np.mean(np.square(errors)):.6f}")
    assert loss == pytest.approx(float(np.mean(np.square(errors))), rel=1e-3)
    assert loss > 1e-4


def test_descending_the_loss_moves_the_gain_to_the_target() -> None:
    targets = anchor_targets(_runs())
    states, inputs = _scalings()
    net = _random_net(bilinear=True)
    anchor = GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    first = float(anchor.loss(net).detach())
    for _ in range(30):
        optimiser.zero_grad()
        loss = anchor.loss(net)
        loss.backward()
        optimiser.step()
    assert float(anchor.loss(net).detach()) < 0.5 * first


def test_the_anchor_setting_is_recorded_only_when_on_and_checked() -> None:
    assert "gain_anchor" not in settings_json(TrainingSettings())
    assert settings_json(TrainingSettings(gain_anchor=10.0))["gain_anchor"] == 10.0
    assert TrainingSettings(gain_anchor=1.0, dictionary=("vy/vx",)).gain_anchor == 1.0  # a dictionary is fine
    for bad in ({"gain_anchor": -1.0}, {"gain_anchor": 1.0, "form": "linear"}):
        with pytest.raises(KoopmanError, match="gain_anchor"):
            TrainingSettings(**bad)


def test_training_with_the_anchor_records_its_targets() -> None:
    from models.koopman_train import train
    settings = TrainingSettings(n_features=4, hidden=(16, 16), seq_len=6, batch_size=32, max_epochs=2,
                                steps_per_epoch=10, patience=2, val_windows=256, mirror_symmetric=True,
                                even_features=1, servo_lag=True, steer_bilinear=True, gain_anchor=10.0)
    result = train(_runs(), 0.025, settings, progress=False)
    recorded = result.model.metadata["gain_anchor_targets"]
    assert len(recorded["single_track"]) == 2 and recorded["runs_with_friction"] == 0
    assert len(recorded["speeds"]) >= 5 and all(v > 0 for v in recorded["yaw_rates"])
    assert all("anchor" in row for row in result.history)
    assert result.model.metadata["settings"]["gain_anchor"] == 10.0


def test_a_known_friction_keeps_samples_beyond_the_linear_range_out() -> None:
    """The same runs on mu = 0.3: the fast bands, whose lateral acceleration is gentle on a
    dry road (< 0.1 g) but a third of the grip here, are no longer anchored."""
    runs = _runs(offset=0.01)
    dry = anchor_targets(runs)
    slippery = anchor_targets(runs, {run.name: 0.3 for run in runs})
    print(f"speeds dry {dry.speeds.tolist()}, mu 0.3 {slippery.speeds.tolist()}")
    assert dry.runs_with_friction == 0 and slippery.runs_with_friction == len(runs)
    assert set(slippery.speeds) < set(dry.speeds)
    assert max(dry.speeds) > max(slippery.speeds)


def test_the_single_track_smoothing_recovers_its_parameters_and_refuses_a_wrong_sign() -> None:
    speeds = np.arange(8.0, 32.0, 2.0)
    yaw_rates = ANCHOR_STEP * speeds / (2.8 + 0.0018 * speeds ** 2)
    assert single_track_gain_fit(speeds, yaw_rates, np.ones_like(speeds)) == pytest.approx([2.8, 0.0018], rel=1e-9)
    yaw_rates[3] = -yaw_rates[3]
    with pytest.raises(KoopmanError, match="wrong way"):
        single_track_gain_fit(speeds, yaw_rates, np.ones_like(speeds))


def test_the_anchor_refuses_states_it_would_read_by_the_wrong_position() -> None:
    targets = anchor_targets(_runs())
    states, inputs = _scalings()
    with pytest.raises(KoopmanError, match="vx, vy, yaw_rate"):
        GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), ("vy", "vx", "yaw_rate", "steer_measured"),
                   INPUTS)
    with pytest.raises(KoopmanError, match="inputs"):
        GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, ("steer", "torque"))

"""The gain anchor's lateral-velocity term (``--gain-anchor-vy``): targets from local fits of
the training runs smoothed through vy / r = b - c v^2, the loss term, the option's checks."""
from __future__ import annotations


import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.koopman import KoopmanError, KoopmanModel  # noqa: E402
from models.koopman_metrics import Trajectory  # noqa: E402
from models.koopman_train import TrainingSettings, settings_json, train  # noqa: E402
from models.koopman_train_anchor import (ANCHOR_SPEEDS, ANCHOR_STEP, ANCHOR_STEPS, GENTLE_GRIP,  # noqa: E402
                                        VY_LENGTH, VY_SPEED_STEP, AnchorTargets, GainAnchor, anchor_targets,
                                        anchor_step_response, lateral_velocity_targets, slip_free_distance,
                                        slip_free_point_fit)
from models.local_lateral_fit import local_fit  # noqa: E402
from test_koopman_symmetric import INPUTS, KNOTS, STATES, _random_net, _scalings  # noqa: E402
from test_koopman_train_anchor import _runs as anchor_runs  # noqa: E402

#: vy / r of the synthetic car at steady state, b - c v^2 (m): it crosses zero at 17 m/s, as
#: the plant's does between 15 and 20 m/s.
NEAR, SPEED_FACTOR = 1.6, 0.0055


def _lateral_step(x: np.ndarray, steer: float, speed: float) -> np.ndarray:
    """A known linear lateral system [vy, r, delta]: the yaw rate grows with the speed, vy
    follows (b - c v^2) r with a lag of its own, so that it is not r times a constant."""
    vy, r, delta = x
    return np.array([0.8 * vy + 0.2 * slip_free_distance(NEAR, SPEED_FACTOR, speed) * r,
                     0.9 * r + 0.004 * speed * delta, 0.8 * delta + 0.2 * steer])


def _runs() -> list[Trajectory]:
    """One run per anchor speed at constant speed of this module's car, the steer a small
    random signal."""
    return anchor_runs(lateral_step=_lateral_step)


def _true_response(speed: float) -> np.ndarray:
    """[vy, r, delta] of the synthetic car ANCHOR_STEPS steps after a step of ANCHOR_STEP."""
    x = np.zeros(3)
    for _ in range(ANCHOR_STEPS):
        x = _lateral_step(x, ANCHOR_STEP, speed)
    return x


def test_targets_are_the_local_fits_vy_smoothed_through_vy_over_r() -> None:
    """Noise-free runs: the fits give the true vy after the step, through zero at 17 m/s;
    and since every pole of the synthetic car is the same at every speed, its vy / r after
    the step is (b - c v^2) times one factor, which the smoothing recovers exactly, also
    between the anchor's even speeds (the odd ones, the 15 m/s speed knot among them)."""
    targets = anchor_targets(_runs())
    vy_targets = lateral_velocity_targets(targets)
    fitted_truth = np.array([_true_response(v) for v in targets.speeds])
    assert np.allclose(vy_targets.fitted_lateral_velocities, fitted_truth[:, 0], rtol=1e-5, atol=1e-8)
    assert vy_targets.speeds.tolist() == np.arange(ANCHOR_SPEEDS[0], ANCHOR_SPEEDS[-1] + 0.5, VY_SPEED_STEP).tolist()
    truth = np.array([_true_response(v) for v in vy_targets.speeds])
    print(f"vy targets {vy_targets.lateral_velocities.round(5).tolist()}, "
          f"largest difference to the truth {np.abs(vy_targets.lateral_velocities - truth[:, 0]).max():.1e} m/s")
    assert np.allclose(vy_targets.lateral_velocities, truth[:, 0], rtol=1e-3, atol=1e-6)
    assert np.allclose(vy_targets.yaw_rates, truth[:, 1], rtol=1e-3)
    assert vy_targets.lateral_velocities[0] > 0 > vy_targets.lateral_velocities[-1]  # crosses zero
    assert np.all(vy_targets.torques == 100.0)  # the bands' median, interpolated
    factor = truth[0, 0] / truth[0, 1] / slip_free_distance(NEAR, SPEED_FACTOR, vy_targets.speeds[0])
    assert vy_targets.slip_free_point == pytest.approx([factor * NEAR, factor * SPEED_FACTOR], rel=1e-3)
    recorded = vy_targets.as_json()
    assert recorded["length"] == VY_LENGTH and recorded["fitted_speeds"] == targets.speeds.tolist()
    assert "fitted_lateral_velocities" not in targets.as_json()  # the yaw anchor's record is as it was


def _stiffening_step(x: np.ndarray, steer: float, speed: float) -> np.ndarray:
    """A lateral system whose vy grows faster than the step at speed, as the plant's does (its
    rear axle takes up more slip at a larger lateral acceleration): a cubic term in r, 12 %
    of vy at 30 m/s after the anchor's step; the yaw rate linear."""
    vy, r, delta = x
    return np.array([0.8 * vy + 0.2 * (slip_free_distance(NEAR, SPEED_FACTOR, speed) * r - 0.03 * speed ** 2 * r ** 3),
                     0.9 * r + 0.02 * speed * delta, 0.8 * delta + 0.2 * steer])


def _step_vy(speed: float, step: float) -> float:
    """The antisymmetric vy of ``_stiffening_step`` ANCHOR_STEPS after a steer step, scaled to ANCHOR_STEP."""
    finals = []
    for sign in (1.0, -1.0):
        x = np.zeros(3)
        for _ in range(ANCHOR_STEPS):
            x = _stiffening_step(x, sign * step, speed)
        finals.append(x[0])
    return (finals[0] - finals[1]) / 2.0 * ANCHOR_STEP / step


def test_the_vy_fits_take_the_samples_up_to_the_steps_own_grip_use() -> None:
    """Where vy stops being linear in the step, the targets move from the small-signal
    response (the gentle samples') to the step's own: the fit at each speed takes the
    samples below the step's lateral acceleration, not those beyond it, whose vy grows
    further (a fit on every sample overshoots the step's)."""
    rng = np.random.default_rng(4)
    runs = []
    for speed in ANCHOR_SPEEDS:  # the steer's amplitude grows over the run to 3 x the step's
        steer = np.linspace(0.001, 0.06, 2000) * np.sin(np.cumsum(rng.uniform(0.05, 0.3, 2000)))
        x, states = np.zeros(3), []
        for k in range(2000):
            states.append([speed, *x])
            x = _stiffening_step(x, steer[k], speed)
        runs.append(Trajectory(f"v{speed:g}", np.array(states), np.c_[np.full(2000, 100.0), steer], STATES, INPUTS))
    targets = anchor_targets(runs)
    vy_targets = lateral_velocity_targets(targets)
    # the step's lateral acceleration (v r / g of the yaw target), at least the gentle bound
    assert targets.lateral_grip_limits == pytest.approx(np.maximum(GENTLE_GRIP, targets.speeds * targets.yaw_rates / 9.81))
    assert targets.lateral_grip_limits[-1] > 3 * GENTLE_GRIP  # the step at 30 m/s: about 0.36 g
    assert vy_targets.as_json()["fitted_grip_limits"] == [round(float(v), 6) for v in targets.lateral_grip_limits]
    assert np.all(targets.lateral_samples >= targets.samples)  # a superset of the gentle samples
    high = targets.speeds >= 20.0
    assert np.all(targets.lateral_samples[high] < 1999)  # and not every sample: some lie beyond the step's
    every_sample = [np.ones(2000, dtype=bool) for _ in runs]
    for speed in (20.0, 24.0, 28.0):
        target = float(np.interp(speed, vy_targets.speeds, vy_targets.lateral_velocities))
        step, small_signal = _step_vy(speed, ANCHOR_STEP), _step_vy(speed, 1e-4)
        overshoot = anchor_step_response(local_fit(runs, every_sample, speed)[0], speed, 100.0)[1]
        print(f"{speed:g} m/s: step {step:+.4f}, small signal {small_signal:+.4f}, target {target:+.4f}, "
              f"every sample {overshoot:+.4f} m/s")
        assert abs(target - step) < 0.4 * abs(small_signal - step)
        assert abs(overshoot - step) > 0.6 * abs(small_signal - step)


def test_the_slip_free_point_fit_recovers_its_parameters_and_refuses_a_wrong_trend() -> None:
    speeds = np.arange(8.0, 32.0, 2.0)
    distances = 1.5 - 0.005 * speeds ** 2
    weights = np.linspace(1.0, 3.0, speeds.size)
    assert slip_free_point_fit(speeds, distances, weights) == pytest.approx([1.5, 0.005], rel=1e-9)
    with pytest.raises(KoopmanError, match="positive b and c"):  # the point moving back with speed
        slip_free_point_fit(speeds, 0.5 + 0.001 * speeds ** 2, weights)


def test_targets_need_the_fitted_lateral_velocities() -> None:
    bare = AnchorTargets(*(np.ones(4) for _ in range(5)))
    with pytest.raises(KoopmanError, match="fitted lateral velocities"):
        lateral_velocity_targets(bare)


def _anchor(with_vy: bool = True) -> GainAnchor:
    targets = anchor_targets(_runs())
    states, inputs = _scalings()
    return GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS,
                      lateral_velocity_targets(targets) if with_vy else None)


def test_the_vy_loss_is_the_error_of_vy_over_r_of_the_exported_models_step_response() -> None:
    """The torch loss equals the same quantity computed on the exported numpy model."""
    targets = anchor_targets(_runs())
    vy_targets = lateral_velocity_targets(targets)
    states, inputs = _scalings()
    net = _random_net(bilinear=True).double()
    anchor = GainAnchor(targets, states, inputs, KNOTS, torch.device("cpu"), STATES, INPUTS, vy_targets)
    with torch.no_grad():
        loss = float(anchor.losses(net.float())["anchor_vy"])
    model = KoopmanModel.from_normalised(net.double().export(states, inputs, (), None, KNOTS), 0.025, STATES, INPUTS)
    commands = np.zeros((2, ANCHOR_STEPS, 2))
    commands[..., 0] = 100.0
    commands[0, :, 1], commands[1, :, 1] = ANCHOR_STEP, -ANCHOR_STEP
    errors = []
    for speed, torque, r_target, vy_target in zip(vy_targets.speeds, vy_targets.torques, vy_targets.yaw_rates,
                                                  vy_targets.lateral_velocities):
        commands[..., 0] = torque
        final = model.predict(np.tile([speed, 0.0, 0.0, 0.0], (2, 1)), commands)[:, -1, 1]
        errors.append(((final[0] - final[1]) / 2 - vy_target) / (r_target * VY_LENGTH))
    print(f"vy anchor loss {loss:.6f}, numpy {np.mean(np.square(errors)):.6f}")
    assert loss == pytest.approx(float(np.mean(np.square(errors))), rel=1e-3)
    assert loss > 1e-4  # a random net is off: the check has something to compare


def test_the_yaw_term_is_the_same_with_and_without_the_vy_term() -> None:
    net = _random_net(bilinear=True)
    with torch.no_grad():
        with_vy, without, alone = _anchor(True).losses(net), _anchor(False).losses(net), _anchor(False).loss(net)
    assert set(without) == {"anchor"} and set(with_vy) == {"anchor", "anchor_vy"}
    assert float(with_vy["anchor"]) == float(without["anchor"]) == float(alone)


def test_descending_the_vy_loss_moves_vy_to_the_target() -> None:
    anchor = _anchor()
    net = _random_net(bilinear=True)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    first = float(anchor.losses(net)["anchor_vy"].detach())
    for _ in range(30):
        optimiser.zero_grad()
        anchor.losses(net)["anchor_vy"].backward()
        optimiser.step()
    last = float(anchor.losses(net)["anchor_vy"].detach())
    print(f"vy anchor loss {first:.4f} -> {last:.4f}")
    assert last < 0.5 * first


def test_the_vy_setting_is_recorded_only_when_on_and_checked() -> None:
    assert "gain_anchor_vy" not in settings_json(TrainingSettings(gain_anchor=10.0))
    on = settings_json(TrainingSettings(gain_anchor=10.0, gain_anchor_vy=3.0))
    assert on["gain_anchor_vy"] == 3.0
    # the fits' recipe, so that a model on the gentle fits' targets is not taken for one of these
    assert on["gain_anchor_vy_fits"] == "grip use below the step's"
    assert "gain_anchor_vy_fits" not in settings_json(TrainingSettings(gain_anchor=10.0))
    for bad in ({"gain_anchor": 10.0, "gain_anchor_vy": -1.0}, {"gain_anchor_vy": 1.0}):  # needs the yaw anchor
        with pytest.raises(KoopmanError, match="gain_anchor_vy"):
            TrainingSettings(**bad)


def _tiny_training(gain_anchor_vy: float) -> dict:
    settings = TrainingSettings(n_features=4, hidden=(16, 16), seq_len=6, batch_size=32, max_epochs=2,
                                steps_per_epoch=10, patience=2, val_windows=256, mirror_symmetric=True,
                                even_features=1, servo_lag=True, steer_bilinear=True, gain_anchor=10.0,
                                gain_anchor_vy=gain_anchor_vy)
    result = train(_runs(), 0.025, settings, progress=False)
    return {"metadata": result.model.metadata, "history": result.history}


def test_training_with_the_vy_term_records_its_targets_and_without_it_nothing() -> None:
    on = _tiny_training(10.0)
    recorded = on["metadata"]["gain_anchor_vy_targets"]
    assert len(recorded["slip_free_point"]) == 2 and all(v > 0 for v in recorded["slip_free_point"])
    assert recorded["fitted_speeds"] == on["metadata"]["gain_anchor_targets"]["speeds"]
    assert len(recorded["speeds"]) == len(recorded["lateral_velocities"]) > len(recorded["fitted_speeds"])
    assert all("anchor_vy" in row for row in on["history"])
    assert on["metadata"]["settings"]["gain_anchor_vy"] == 10.0
    off = _tiny_training(0.0)
    assert "gain_anchor_vy_targets" not in off["metadata"] and "gain_anchor_vy" not in off["metadata"]["settings"]
    assert not any("anchor_vy" in row for row in off["history"])

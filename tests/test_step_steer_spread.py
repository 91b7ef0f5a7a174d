"""The step-steer-over-seeds study: its error measure, tables, figure and CLI refusals."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from studies import step_steer_spread as study


class Scaled:
    """A 'model' that replays the plant's step response with its yaw rate times ``gain``."""

    n_x = 4

    def __init__(self, plant: dict, gain: float) -> None:
        self.by_speed = {round(float(states[0, 0]), 3): states for states, _ in plant.values()}
        self.gain = gain

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        states = self.by_speed[round(float(x0[0, 0]), 3)][1:].copy()
        states[:, 2] *= self.gain
        return states[None]


class GainAndDrift:
    """A 'model' whose yaw rate is ``gain`` times the plant's response to the command's
    steer (linear in the steer: the plant's at +0.02 rad scaled) plus ``drift`` rad/s, and
    whose wheel angle is ``wheel`` times the plant's."""

    n_x = 4

    def __init__(self, plant: dict, gain: float, drift: float, wheel: float = 1.0) -> None:
        self.by_speed = {round(float(states[0, 0]), 3): states for states, _ in plant.values()}
        self.gain, self.drift, self.wheel = gain, drift, wheel

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        states = self.by_speed[round(float(x0[0, 0]), 3)][1:].copy()
        share = inputs[0, -1, 1] / 0.02  # +1, 0 or -1: the step, no steer, the mirrored step
        states[:, 2] = self.gain * share * states[:, 2] + self.drift
        states[:, 3] *= self.wheel * share
        return states[None]


@pytest.fixture(scope="module")
def plant() -> dict:
    return study.plant_responses()


def test_yaw_error_is_measured_against_the_plant_after_one_second(plant) -> None:
    assert study.error_parts_pct(Scaled(plant, 1.0), plant)["total"] == pytest.approx([0.0] * 4, abs=1e-9)
    assert study.error_parts_pct(Scaled(plant, 0.9), plant)["total"] == pytest.approx([-10.0] * 4)
    # The plant's yaw response grows with speed: the learned models must follow it.
    finals = [states[-1, 2] for states, _ in plant.values()]
    assert all(b > a for a, b in zip(finals, finals[1:]))


def test_error_splits_into_drift_and_antisymmetric_gain(plant) -> None:
    model = GainAndDrift(plant, gain=0.92, drift=-0.004, wheel=0.95)
    parts = study.error_parts_pct(model, plant)
    finals = [states[-1, 2] for states, _ in plant.values()]
    assert parts["antisymmetric"] == pytest.approx([-8.0] * 4)
    assert parts["drift"] == pytest.approx([-0.4 / r for r in finals])
    assert parts["wheel_angle"] == pytest.approx([-5.0] * 4)
    # For a model linear in the steer the two parts add up to the total error.
    total = parts["total"]
    assert total == pytest.approx([a + d for a, d in zip(parts["antisymmetric"], parts["drift"])])
    symmetric = study.error_parts_pct(GainAndDrift(plant, gain=1.0, drift=0.0), plant)
    assert symmetric["drift"] == pytest.approx([0.0] * 4, abs=1e-12)
    assert symmetric["antisymmetric"] == pytest.approx([0.0] * 4, abs=1e-9)


PLANT_VY = [0.0722, 0.0382, -0.0641, -0.2425]


def _result(errors: dict[str, list[list[float]]], vy_errors: dict[str, list[list[float]]] | None = None) -> dict:
    seeds = list(range(len(next(iter(errors.values())))))
    vy_errors = vy_errors or {label: [[0.0] * 4] * len(rows) for label, rows in errors.items()}
    rmse = {"vy": 0.15, "yaw_rate": 0.05}
    return {"speeds": [10.0, 15.0, 20.0, 25.0], "plant_yaw_rate": [0.067, 0.094, 0.114, 0.128],
            "plant_vy": PLANT_VY, "seeds": seeds, "data_dir": "data/wide",
            "bicycle": [{"seed": s, "rmse_1s": {"vy": 0.23, "yaw_rate": 0.08}} for s in seeds],
            "variants": [{"label": label, "seeds": [{"seed": s, "yaw_error_pct": e, "rmse_1s": rmse, "epochs": "9/12",
                                                     "error_parts_pct": {"drift": [s, 0.0, 0.0, 0.0],
                                                                         "antisymmetric": list(e),
                                                                         "wheel_angle": [float("nan")] * 4},
                                                     "vy_error": vy_errors[label][s]}
                                                    for s, e in enumerate(rows)]}
                         for label, rows in errors.items()]}


def test_tables_count_the_seeds_within_tolerance_at_every_speed(tmp_path: Path) -> None:
    result = _result({"a": [[1.0, -2.0, 4.9, 0.0], [-12.4, -2.7, -1.7, 1.2], [6.0, 0.0, 0.0, 0.0]],
                      "b": [[0.0, 0.0, 0.0, 0.0]] * 3})
    text = study.markdown(result)
    per_variant = text.split("## Lateral velocity")[0]
    summary = {line.split(" | ")[0].strip("| "): line for line in per_variant.splitlines() if " of 3 |" in line}
    assert "| 1 of 3 |" in summary["a"] and "| 3 of 3 |" in summary["b"]
    assert "| a | 1 | -12.4 | -2.7 | -1.7 | +1.2 | 12.4 |" in text
    assert "-1.8 ± 9.5" in summary["a"]  # mean and sample sd over the seeds at 10 m/s
    assert "## Where the error comes from" in text
    assert "| a | yaw rate with the steer at 0 (drift, % of the plant's r) | +1.0 ± 1.0 | +0.0 ± 0.0 |" in text
    assert "wheel angle after 1 s" not in text  # no model here has a wheel angle
    study.plot(result, tmp_path / "spread.png")
    assert (tmp_path / "spread.png").stat().st_size > 10_000


def test_the_gain_sweep_measures_the_gain_at_every_speed(plant) -> None:
    """The sweep's speeds reach past the four of the target and cover the knots' range; a
    model with 0.92 times the plant's antisymmetric response reads -8 % at each of them."""
    speeds = (4.0, 13.0, 34.0)
    sweep = study.plant_responses(speeds)
    assert list(sweep) == list(speeds)
    assert study.error_parts_pct(GainAndDrift(sweep, gain=0.92, drift=0.003), sweep)["antisymmetric"] \
        == pytest.approx([-8.0] * 3)
    assert min(study.GAIN_SPEEDS) < 10.0 and max(study.GAIN_SPEEDS) > 25.0
    assert all(b - a == 2.0 for a, b in zip(study.GAIN_SPEEDS, study.GAIN_SPEEDS[1:]))


def test_the_gain_sweep_table_and_panel(tmp_path: Path) -> None:
    result = _result({"a": [[1.0, -2.0, 4.9, 0.0], [-12.4, -2.7, -1.7, 1.2]], "b": [[0.0, 0.0, 0.0, 0.0]] * 2})
    result["gain_speeds"], result["speed_knots"] = [4.0, 6.0, 8.0], [3.0, 6.0, 10.0]
    for entry, rows in zip(result["variants"], ([[-4.0, -8.0, 2.0], [-6.0, -6.0, 0.0]], [[0.0, 0.0, 0.0]] * 2)):
        for seed, row in zip(entry["seeds"], rows):
            seed["gain_error_pct"] = row
    text = study.markdown(result)
    assert "## The gain over speed" in text and "knots are 3, 6, 10 m/s" in text
    assert "| a | -5.0 (1.4) | -7.0 (1.4) | +1.0 (1.4) |" in text
    assert "| b | +0.0 (0.0) | +0.0 (0.0) | +0.0 (0.0) |" in text
    study.plot(result, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 10_000
    # A result written before the sweep existed renders without it.
    del result["gain_speeds"]
    assert "## The gain over speed" not in study.markdown(result)


def test_the_anchor_targets_are_compared_with_the_plant_and_the_model_with_its_target(plant) -> None:
    """A model whose recorded target is the plant's own single-track fit reads ~0 % against
    the plant; the table then gives the model's error against its target."""
    speeds = np.array(list(plant))
    finals = np.array([states[-1, 2] for states, _ in plant.values()])
    # L, K through the plant's responses at the first and last speeds: exact there.
    ratio = 0.02 * speeds / finals
    understeer = (ratio[-1] - ratio[0]) / (speeds[-1] ** 2 - speeds[0] ** 2)
    length = ratio[0] - understeer * speeds[0] ** 2
    metadata = {"gain_anchor_targets": {"single_track": [length, understeer], "step": 0.02}}
    errors = study.anchor_target_error_pct(metadata, plant)["anchor_target_error_pct"]
    assert errors[0] == pytest.approx(0.0, abs=1e-9) and errors[-1] == pytest.approx(0.0, abs=1e-9)
    assert max(map(abs, errors)) < 2.0  # the single-track form follows the plant in between
    assert study.anchor_target_error_pct({}, plant) == {}
    result = _result({"anchored": [[0.0, 0.0, 0.0, 0.0]], "plain": [[0.0, 0.0, 0.0, 0.0]]})
    result["variants"][0]["seeds"][0]["anchor_target_error_pct"] = [-5.0, 0.0, 0.0, 10.0]
    result["variants"][0]["seeds"][0]["error_parts_pct"]["antisymmetric"] = [-5.0, 1.0, 0.0, 0.0]
    text = study.markdown(result)
    assert "## The gain anchor's targets" in text
    assert "| anchored | 0 | -5.0 / +0.0 / +0.0 / +10.0 | +0.0 / +1.0 / +0.0 / -9.1 |" in text
    assert "| plain | 0 |" not in text.split("## The gain anchor's targets")[1].split("##")[0]


def test_cli_refuses_a_missing_data_set_and_no_seeds(tmp_path: Path, capsys) -> None:
    assert study.main(["--data", str(tmp_path / "absent"), "--out", str(tmp_path)]) == 2
    assert "no data set (READY missing)" in capsys.readouterr().err
    assert study.main(["--data", str(tmp_path), "--seeds", "", "--out", str(tmp_path)]) == 2
    assert "--seeds must name at least one seed" in capsys.readouterr().err
    assert study.main(["--data", str(tmp_path), "--variants", f"0,{len(study.VARIANTS)}", "--out", str(tmp_path)]) == 2
    assert f"--variants must name variants among 0-{len(study.VARIANTS) - 1}" in capsys.readouterr().err


def test_step_steer_vy_is_measured_against_the_plant_and_its_goal_counted(plant) -> None:
    errors = study.vy_error(Scaled(plant, 0.9), plant)  # Scaled changes the yaw rate only
    assert errors == pytest.approx([0.0] * 4, abs=1e-12)
    # 10 m/s: absolute 0.01 m/s; 15-25 m/s: 10 % of the plant's vy.
    assert study.vy_within_goal([0.0099, 0.0038, -0.0064, 0.0242], PLANT_VY)
    assert not study.vy_within_goal([0.0101, 0.0, 0.0, 0.0], PLANT_VY)
    assert not study.vy_within_goal([0.0, 0.0039, 0.0, 0.0], PLANT_VY)
    assert not study.vy_within_goal([0.0, 0.0, 0.0, -0.0245], PLANT_VY)
    vy_errors = [[0.0, 0.0, 0.0, 0.0], [0.02, 0.0, 0.0, 0.0], [0.0, 0.0, 0.01, 0.0]]
    text = study.markdown(_result({"a": [[0.0] * 4] * 3}, {"a": vy_errors}))
    section = text.split("## Lateral velocity")[1].split("## Where")[0]
    vy_lines = [line for line in section.splitlines() if line.startswith("| a |")]
    assert len(vy_lines) == 1 and vy_lines[0].endswith("| 1 of 3 |")
    assert "0.0067 ± 0.0115" in vy_lines[0]  # 10 m/s: mean and sample sd of 0, 0.02, 0

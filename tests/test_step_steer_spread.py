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


@pytest.fixture(scope="module")
def plant() -> dict:
    return study.plant_responses()


def test_yaw_error_is_measured_against_the_plant_after_one_second(plant) -> None:
    assert study.yaw_errors_pct(Scaled(plant, 1.0), plant) == pytest.approx([0.0] * 4, abs=1e-9)
    assert study.yaw_errors_pct(Scaled(plant, 0.9), plant) == pytest.approx([-10.0] * 4)
    # The plant's yaw response grows with speed: the learned models must follow it.
    finals = [states[-1, 2] for states, _ in plant.values()]
    assert all(b > a for a, b in zip(finals, finals[1:]))


def _result(errors: dict[str, list[list[float]]]) -> dict:
    seeds = list(range(len(next(iter(errors.values())))))
    rmse = {"vy": 0.15, "yaw_rate": 0.05}
    return {"speeds": [10.0, 15.0, 20.0, 25.0], "plant_yaw_rate": [0.067, 0.094, 0.114, 0.128],
            "seeds": seeds, "data_dir": "data/wide",
            "bicycle": [{"seed": s, "rmse_1s": {"vy": 0.23, "yaw_rate": 0.08}} for s in seeds],
            "variants": [{"label": label, "seeds": [{"seed": s, "yaw_error_pct": e, "rmse_1s": rmse, "epochs": "9/12"}
                                                    for s, e in enumerate(rows)]}
                         for label, rows in errors.items()]}


def test_tables_count_the_seeds_within_tolerance_at_every_speed(tmp_path: Path) -> None:
    result = _result({"a": [[1.0, -2.0, 4.9, 0.0], [-12.4, -2.7, -1.7, 1.2], [6.0, 0.0, 0.0, 0.0]],
                      "b": [[0.0, 0.0, 0.0, 0.0]] * 3})
    text = study.markdown(result)
    summary = {line.split(" | ")[0].strip("| "): line for line in text.splitlines()[-2:]}
    assert "| 1 of 3 |" in summary["a"] and "| 3 of 3 |" in summary["b"]
    assert "| a | 1 | -12.4 | -2.7 | -1.7 | +1.2 | 12.4 |" in text
    assert "-1.8 ± 9.5" in summary["a"]  # mean and sample sd over the seeds at 10 m/s
    study.plot(result, tmp_path / "spread.png")
    assert (tmp_path / "spread.png").stat().st_size > 10_000


def test_cli_refuses_a_missing_data_set_and_no_seeds(tmp_path: Path, capsys) -> None:
    assert study.main(["--data", str(tmp_path / "absent"), "--out", str(tmp_path)]) == 2
    assert "no data set (READY missing)" in capsys.readouterr().err
    assert study.main(["--data", str(tmp_path), "--seeds", "", "--out", str(tmp_path)]) == 2
    assert "--seeds must name at least one seed" in capsys.readouterr().err

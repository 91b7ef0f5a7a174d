"""models.servo_fit: the steering servo's time constant from command and wheel angle."""
import math

import numpy as np
import pytest

from models.errors import ModelError
from models.servo_fit import fit_servo_lag

TS = 0.025


def servo_run(tau: float, rate_limit: float, n: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A held command of random steps through a first-order lag, rate limited, sampled at TS."""
    rng = np.random.default_rng(seed)
    command = np.repeat(rng.uniform(-0.05, 0.05, n // 20), 20)
    measured = np.zeros(n)
    fraction = 1.0 - math.exp(-TS / tau)
    for k in range(n - 1):
        move = fraction * (command[k] - measured[k])
        measured[k + 1] = measured[k] + float(np.clip(move, -rate_limit * TS, rate_limit * TS))
    return command, measured


def test_recovers_the_time_constant_of_a_lag() -> None:
    fit = fit_servo_lag([servo_run(0.09, rate_limit=10.0)], TS)
    assert fit.time_constant_s == pytest.approx(0.09, rel=1e-9)
    assert fit.one_step_rmse_rad < 1e-12


def test_steps_at_the_rate_limit_are_left_out() -> None:
    run = servo_run(0.09, rate_limit=0.5)
    with_limit = fit_servo_lag([run], TS, rate_limit=0.5)
    assert with_limit.time_constant_s == pytest.approx(0.09, rel=1e-6)
    # without leaving them out the rate-limited steps read as a slower servo
    assert fit_servo_lag([run], TS).time_constant_s > 0.095


def test_too_few_steps_and_no_lag_are_refused() -> None:
    command, measured = servo_run(0.09, rate_limit=10.0, n=100)
    with pytest.raises(ModelError, match="usable steps"):
        fit_servo_lag([(command, measured)], TS)
    with pytest.raises(ModelError, match="not a lag"):
        fit_servo_lag([(command, -measured)], TS, min_steps=10)
    with pytest.raises(ModelError, match="equal 1-d arrays"):
        fit_servo_lag([(command, measured[:-1])], TS)

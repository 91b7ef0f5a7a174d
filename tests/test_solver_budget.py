"""The solver's wall-clock budget in real time (issue 37 item 5): NMPC stops IPOPT at the
budget and falls back to its last converged plan; the ECU sets the budget in real time only,
so lockstep runs stay independent of the machine."""
from __future__ import annotations

import can
import numpy as np
import pytest

from controller.base import SolverStatus, VehicleSample
from controller.reference import ReferencePath
from controller.registry import create_controller
from firmware_sim.config import EcuConfig
from firmware_sim.ecu import Ecu
from firmware_sim.errors import ConfigError

SAMPLE = VehicleSample(12.0, 0.1, 0.05, 0.01, 0.2, 0.0, 0.01, 0.0, 12.0)


def _stepped(budget: float | None, steps: int = 3):
    controller = create_controller("nmpc")
    controller.set_path(ReferencePath.double_lane_change())
    controller.set_time_budget(budget)
    return [controller.step(SAMPLE) for _ in range(steps)]


def test_a_budget_too_short_to_converge_falls_back_within_the_limits() -> None:
    unlimited = _stepped(None)
    assert all(debug.status == SolverStatus.SOLVED for _, debug in unlimited)
    starved = _stepped(1e-6)  # below one IPOPT iteration
    assert all(debug.status == SolverStatus.MAX_ITERATIONS and debug.fallback for _, debug in starved)
    assert all(abs(command.steer_angle) <= 0.3 for command, _ in starved)
    # no budget again: the same commands as a controller that never had one
    again = _stepped(None)
    assert [c.steer_angle for c, _ in again] == [c.steer_angle for c, _ in unlimited]
    with pytest.raises(ValueError, match="positive number of seconds"):
        create_controller("nmpc").set_time_budget(float("nan"))


class _Recorder:
    """A controller double that records the budget the ECU gives it."""

    def __init__(self) -> None:
        self.budgets: list[float | None] = []

    def set_time_budget(self, seconds: float | None) -> None:
        self.budgets.append(seconds)


@pytest.mark.parametrize("lockstep, expected", [(True, []), (False, [0.015])])
def test_the_ecu_gives_the_budget_in_real_time_only(lockstep: bool, expected: list[float]) -> None:
    recorder = _Recorder()
    with can.Bus(interface="virtual", channel=f"budget-{lockstep}") as bus:
        ecu = Ecu(bus, "nmpc", {}, lockstep=lockstep, controller_factory=lambda name: recorder)
        assert ecu.load_error is None
    assert recorder.budgets == expected
    with pytest.raises(ConfigError, match="solver_budget_ms"):
        EcuConfig(solver_budget_ms=25)
    assert np.isclose(EcuConfig().solver_budget_ms, 15)


class _CappedSolver:
    """IPOPT capped at ``iterations`` per solve, the cap reported as the wall-clock budget's
    (``Maximum_WallTime_Exceeded``): a deterministic stand-in for a budget that a cold start
    runs past and a warm start does not."""

    def __init__(self, problem, iterations: int) -> None:
        import casadi as ca

        self._solver = ca.nlpsol("capped", "ipopt", problem, {
            "expand": True, "print_time": False, "record_time": True,
            "ipopt": {"print_level": 0, "sb": "yes", "max_iter": iterations, "warm_start_init_point": "yes"}})

    def __call__(self, **arguments):
        return self._solver(**arguments)

    def stats(self) -> dict:
        stats = dict(self._solver.stats())
        if stats["return_status"] == "Maximum_Iterations_Exceeded":
            stats["return_status"] = "Maximum_WallTime_Exceeded"
        return stats


def test_a_solve_stopped_by_the_budget_is_carried_on_at_the_next_step() -> None:
    """A cold start takes more than 6 IPOPT iterations here, a warm one 5-6. With 6 per step, the
    first step runs out; the next one goes on from its iterate and converges, and so does
    every step after it. Starting cold again each time, as before, never converged: 12
    fallbacks in a row, which the ECU turns into SAFE_STOP after 4."""
    controller = create_controller("nmpc")
    controller.set_path(ReferencePath.double_lane_change())
    controller._solver = _CappedSolver(controller._problem, 6)
    steps = [controller.step(SAMPLE)[1] for _ in range(12)]
    print([(debug.status.name, debug.iterations) for debug in steps])
    assert steps[0].status == SolverStatus.MAX_ITERATIONS and steps[0].fallback
    assert all(debug.status == SolverStatus.SOLVED and not debug.fallback for debug in steps[1:])

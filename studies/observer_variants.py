"""The observer's design questions, measured (``make observer-variants``; docs/eso.md).

ESO-DKMPC as shipped against variants that each change one design choice, and DKMPC (no
observer), in closed loop without CAN (``studies.closed_loop``) on the two lane changes
without a disturbance and on the straight-curve-straight path under three constant
disturbances. Every variant starts from the tuning file's ``[eso-dkmpc]`` table:

- ``no innovation bound``: ``eso_innovation_limit`` 0 (g2 of eq. 13 the identity);
- ``w on vy, yaw rate only``: the estimate used on the two physical lateral rows of the
  lifted state only (nd = 2 instead of n_z), the other rows' estimate dropped;
- ``fixed bound (no widening)``: ``eso_innovation_persistence`` 0 (the bound never widens;
  the shipped tuning widens it while the innovation keeps its sign beyond it,
  results/observer_tuning_refine.md);
- ``widening at any lateral acceleration``: ``eso_widening_lateral_accel`` 0 (the shipped
  widening without its gate, so it widens in manoeuvres too);
- ``bias estimate off``: ``yaw_rate_bias_pole`` 1 (the shipped tuning has it on);
- ``course-angle cost``: the yaw rows of the QP's cost on the course angle (heading plus
  vy / vx, vy predicted, affine in the steering) instead of the heading, on top of the
  shipped heading target;
- ``slip target 0.02 / 0.003``: the heading target on the measured side slip
  (``controller.steady_slip``) with ``slip_target_limit`` 0.02 rad and ``slip_target_gate``
  0.003 rad instead of the tuned values (``make tune-slip-target``); a design measurement
  of the target's sensitivity, not a tuned result.

The course-angle cost is not in the product; this module builds it for the comparison only.
Reported: e_Y RMSE (cm) and the steady offset (cm): the mean e_Y over the run's last 2 s,
which on ``straight_curve`` lie on its final straight.

Usage: ``python -m studies.observer_variants --out DIR``.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from controller.dkmpc import Dkmpc
from controller.eso_dkmpc import LATERAL_ROWS, EsoDkmpc
from controller.tuning import load_tuning
from hil.errors import HilError
from hil.scenario import load_scenario
from models.disturbance import Disturbances
from models.koopman import KoopmanModel
from studies.closed_loop import run_closed_loop

#: The steady window at a run's end (s).
WINDOW_S = 2.0
#: (label, scenario, ``[disturbances]`` table or None).
CASES: tuple[tuple[str, str, dict[str, Any] | None], ...] = (
    ("lane change, high mu", "dlc_high_mu", None),
    ("lane change, low mu", "dlc_low_mu", None),
    ("straight-curve, offset 0.02 rad", "straight_curve", {"steer_offset_rad": 0.02}),
    ("straight-curve, wind 800 N", "straight_curve", {"crosswind_force_n": 800.0, "crosswind_cp_m": 0.6}),
    ("straight-curve, bank 6 %", "straight_curve", {"bank_angle_rad": 0.06}),
    ("straight-curve, yaw-rate bias 0.01 rad/s", "straight_curve", {"yaw_rate_bias_rad_s": 0.01}),
)


class LateralRowsOnly(EsoDkmpc):
    """ESO-DKMPC whose estimate acts on the vy and yaw-rate rows only (nd = 2)."""

    def disturbance(self, observed_state: np.ndarray) -> np.ndarray:
        """w_hat (n_z,) with every row but vy and the yaw rate zeroed."""
        mask = np.zeros(observed_state.shape[0])
        mask[list(LATERAL_ROWS)] = 1.0
        return super().disturbance(observed_state) * mask


class CourseAngleQp:
    """A ``SteeringQp`` wrapper whose yaw cost rows act on the course angle: the pose's yaw
    row plus vy / vx (vy at the same step, affine in the steering: free + gain U)."""

    def __init__(self, qp: Any, speed: Callable[[], float]) -> None:
        self.qp, self.speed = qp, speed

    def solve(self, pose_jacobian: np.ndarray, pose_offset: np.ndarray, previous_steer: float,
              state_gain: np.ndarray, state_free: np.ndarray, warm_steer: np.ndarray, weights: Any = None,
              yaw_rate_bound: float = math.inf) -> Any:
        """``SteeringQp.solve`` with (Np, 3, Nc) / (Np, 3) pose rows whose yaw is the course."""
        vx = max(self.speed(), 1.0)
        jacobian, offset = pose_jacobian.copy(), pose_offset.copy()
        jacobian[:, 2, :] += state_gain[:, 1, :] / vx
        offset[:, 2] += state_free[:, 1] / vx
        return self.qp.solve(jacobian, offset, previous_steer, state_gain, state_free, warm_steer, weights,
                             yaw_rate_bound)


class CourseAngleCost(EsoDkmpc):
    """ESO-DKMPC with the course-angle cost of :class:`CourseAngleQp`."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._vx = 0.0
        self.qp = CourseAngleQp(self.qp, lambda: self._vx)

    def step(self, sample: Any) -> Any:
        self._vx = sample.vx
        return super().step(sample)


def variants() -> dict[str, Callable[[], Any]]:
    """Label -> a builder of the controller, each from the tuning file."""
    tuning = load_tuning()
    model = KoopmanModel.load()
    table, longitudinal = tuning.eso_dkmpc, tuning.longitudinal
    return {
        "DKMPC": lambda: Dkmpc(model, tuning.dkmpc, longitudinal),
        "ESO-DKMPC (shipped)": lambda: EsoDkmpc(model, table, longitudinal),
        "no innovation bound": lambda: EsoDkmpc(model, dataclasses.replace(table, eso_innovation_limit=0.0),
                                                longitudinal),
        "fixed bound (no widening)": lambda: EsoDkmpc(
            model, dataclasses.replace(table, eso_innovation_persistence=0.0), longitudinal),
        "widening at any lateral acceleration": lambda: EsoDkmpc(
            model, dataclasses.replace(table, eso_widening_lateral_accel=0.0), longitudinal),
        "w on vy, yaw rate only": lambda: LateralRowsOnly(model, table, longitudinal),
        "bias estimate off": lambda: EsoDkmpc(model, dataclasses.replace(table, yaw_rate_bias_pole=1.0),
                                              longitudinal),
        "course-angle cost": lambda: CourseAngleCost(model, table, longitudinal),
        "slip target 0.02 / 0.003": lambda: EsoDkmpc(model, dataclasses.replace(
            table, slip_target_limit=0.02, slip_target_gate=0.003), longitudinal),
    }


def measure(build: Callable[[], Any], scenario_name: str, disturbance: dict[str, Any] | None) -> tuple[float, float]:
    """(e_Y RMSE, steady offset) in m of one run; NaN for both when it did not complete."""
    scenario = load_scenario(scenario_name)
    if disturbance is not None:
        scenario = dataclasses.replace(scenario, disturbances=Disturbances.from_mapping(disturbance, scenario_name))
    result = run_closed_loop(scenario, build())
    if not result.completed:
        return float("nan"), float("nan")
    trace = result.trace
    window = trace.time_s >= trace.time_s[-1] - WINDOW_S
    return float(result.tracking.lateral.rmse), float(np.mean(trace.lateral_error[window]))


def report(rows: dict[str, dict[str, tuple[float, float]]]) -> str:
    """The markdown table: a row per variant, RMSE / steady offset (cm) per case."""
    lines = ["# The observer's design choices, measured", "",
             "Written by `make observer-variants` (`python -m studies.observer_variants`; the variants in its "
             "docstring). Closed loop without CAN. Each cell: e_Y RMSE / steady offset (mean e_Y over the "
             f"run's last {WINDOW_S:g} s; on `straight_curve` its final straight), cm; '-' did not complete.", "",
             "| variant | " + " | ".join(label for label, _, _ in CASES) + " |",
             "|---|" + "---|" * len(CASES)]
    for name, cells in rows.items():
        shown = [("-" if np.isnan(r) else f"{r * 100:.2f} / {o * 100:+.2f}") for r, o in
                 (cells[label] for label, _, _ in CASES)]
        lines.append(f"| {name} | " + " | ".join(shown) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.observer_variants", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for observer_variants.md")
    args = parser.parse_args(argv)
    if not args.out.is_dir():
        print(f"error: --out {args.out}: no such folder", file=sys.stderr)
        return 1
    try:
        rows = {name: {label: measure(build, scenario, table) for label, scenario, table in CASES}
                for name, build in variants().items()}
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    text = report(rows)
    (args.out / "observer_variants.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

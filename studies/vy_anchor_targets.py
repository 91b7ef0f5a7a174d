"""The lateral velocity's anchor targets against the plant: where the step-steer vy goal's
error comes from.

The gain anchor's vy term (``models/koopman_train_anchor.py``, ``--gain-anchor-vy``) holds
the model's vy 1 s after a steer step of 0.02 rad to targets from local linear fits of the
training data. This check puts, at each speed, the plant's own step-steer vy (the goal of
issue 40) beside:

- the plant's small-signal vy: its response to a step of a quarter of 0.02 rad, times 4
  (the antisymmetric part, so that the torque's share cancels), which a fit on gentle
  samples can hold;
- the vy of a local fit on the gentle samples (grip use < ``GENTLE_GRIP``), the targets'
  source until 2026-12-08;
- the vy of the fit at the step's amplitude (samples below the step's own grip use,
  ``vy_grip_limit``), their source since;
- the smoothed target (``lateral_velocity_targets``), and the one the same smoothing gives
  on the gentle fits (the targets until 2026-12-08).

The fits take every run of the data set (a training takes its training runs only). It
writes nothing: the table goes to standard output.

    python -m studies.vy_anchor_targets --data data/wide
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from models.koopman_data import load_trajectories
from models.koopman_train_anchor import (ANCHOR_STEP, GENTLE_GRIP, anchor_step_response, anchor_targets,
                                        lateral_velocity_targets)
from models.local_lateral_fit import INPUTS, STATES, band_segments, friction_of_runs, local_fit, signals
from models.data import speed_hold_torque
from models.vehicle import FourWheelVehicle, PlantModel, VehicleCommand
from studies.model_fidelity import LEAD_IN_SECONDS, STEP_SECONDS, TS

#: Speeds of the table (m/s): the step-steer goal's.
SPEEDS = (10.0, 15.0, 20.0, 22.0, 25.0, 26.0, 28.0, 30.0)
#: The small-signal step, as a fraction of the anchor's.
SMALL_FRACTION = 0.25


def plant_final_vy(speed: float, step: float) -> float:
    """The plant's vy (m/s) STEP_SECONDS after a steer step of ``step`` rad from straight
    driving at ``speed``, the speed held, as ``studies.model_fidelity.plant_step_steer``
    drives it (whose step is fixed at its STEP_STEER)."""
    vehicle = FourWheelVehicle()
    vehicle.reset(vx=speed)
    drag = PlantModel(vehicle.params).drag_factor
    lead, steps = round(LEAD_IN_SECONDS / TS), round(STEP_SECONDS / TS)
    out = vehicle.outputs()
    for k in range(lead + steps):
        torque = speed_hold_torque(vehicle.params, drag, out.vx, speed)
        out = vehicle.step(VehicleCommand(drive_torque=torque, steer_angle=step if k >= lead else 0.0), TS)
    return float(out.vy)


def plant_vy(speed: float, step: float) -> float:
    """The plant's antisymmetric vy (m/s) 1 s after a steer step of ``step`` rad, scaled to
    ANCHOR_STEP: (vy(+step) - vy(-step)) / 2 x ANCHOR_STEP / step."""
    up, down = (plant_final_vy(speed, sign * step) for sign in (1.0, -1.0))
    return (up - down) / 2.0 * ANCHOR_STEP / step


def rows(data: Path) -> list[dict[str, float]]:
    """One row per SPEEDS: the plant's vy at the step and in the small signal, the gentle
    and the amplitude fits' vy and the smoothed target (m/s), and the amplitude fit's grip
    limit."""
    runs = load_trajectories(data, states=STATES, inputs=INPUTS)
    friction = friction_of_runs(data)
    targets = anchor_targets(runs, friction)
    vy_targets = lateral_velocity_targets(targets)
    grip_use = [signals(run, friction.get(run.name, 1.0)).combined_grip for run in runs]
    gentle = [use < GENTLE_GRIP for use in grip_use]
    # the same smoothing (lateral_velocity_targets) on the gentle fits, the targets until 2026-12-08
    responses = np.array([anchor_step_response(local_fit(runs, gentle, float(v))[0], float(v), float(t))
                          for v, t in zip(targets.speeds, targets.torques)])
    gentle_targets = lateral_velocity_targets(dataclasses.replace(
        targets, fitted_lateral_velocities=responses[:, 1], lateral_fit_yaw_rates=responses[:, 2],
        lateral_samples=targets.samples))
    out = []
    for speed in SPEEDS:
        limit = float(np.interp(speed, targets.speeds, targets.lateral_grip_limits))
        fitted = {}
        for name, bound in (("gentle", GENTLE_GRIP), ("amplitude", limit)):
            masks = [use < bound for use in grip_use]
            fit, _ = local_fit(runs, masks, speed)
            torque = float(np.median(np.concatenate([s.inputs[:, 0] for s in band_segments(runs, masks, speed)])))
            fitted[name] = float(anchor_step_response(fit, speed, torque)[1])
        out.append({"speed": speed, "plant": plant_vy(speed, ANCHOR_STEP),
                    "plant_small": plant_vy(speed, SMALL_FRACTION * ANCHOR_STEP), "gentle": fitted["gentle"],
                    "amplitude": fitted["amplitude"], "grip_limit": limit,
                    "target": float(np.interp(speed, vy_targets.speeds, vy_targets.lateral_velocities)),
                    "gentle_target": float(np.interp(speed, gentle_targets.speeds, gentle_targets.lateral_velocities))})
    return out


def markdown(table: list[dict[str, float]], data: Path) -> str:
    """The rows as a table, each fit's and the target's error against the plant's step in %."""
    def pct(value: float, plant: float) -> str:
        return f"{value:+.4f} ({100.0 * (value / plant - 1.0):+.1f} %)"
    lines = [f"vy 1 s after a steer step of {ANCHOR_STEP} rad (m/s; in brackets against the plant's), "
             f"fits on every run of {data}:", "",
             "| speed (m/s) | plant | plant, small signal | gentle fit | fit at the step's amplitude (grip use <) "
             "| target | target from the gentle fits |", "|---|---|---|---|---|---|---|"]
    for r in table:
        lines.append(f"| {r['speed']:g} | {r['plant']:+.4f} | {pct(r['plant_small'], r['plant'])} "
                     f"| {pct(r['gentle'], r['plant'])} | {pct(r['amplitude'], r['plant'])} ({r['grip_limit']:.2f}) "
                     f"| {pct(r['target'], r['plant'])} | {pct(r['gentle_target'], r['plant'])} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.vy_anchor_targets", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/wide"), help="a data set of the plant's runs")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        parser.error(f"--data {args.data}: no such data set (make train generates data/wide)")
    print(markdown(rows(args.data), args.data), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

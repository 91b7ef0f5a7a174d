"""The actuator terms of the steering QP, measured (``make delay-compensation``; docs/tuning.md).

ESO-DKMPC, DKMPC and LMPC in closed loop without CAN (``studies.closed_loop``) on the two
lane changes of Tables II-III (``dlc_high_mu``, ``dlc_low_mu``), each with four settings of
the two optional tuning fields (issue 37), every other field the tuning file's:

- ``off``: as shipped (both 0);
- ``rate rows``: ``qp_steer_rate_limit`` = the plant's steering rate limit
  (models/vehicle.toml ``[actuators] steer_rate_limit``, 1.0 rad/s);
- ``delay comp.``: ``delay_compensation_s`` = the plant's command dead time (below), or
  :data:`TASK_TIME_S` where it has none (the fixed part must be > 0 to be on), plus the
  sample's age the runner's timing gives (0 or 5 ms: :class:`AgedSamples`);
- ``both``.

Plants: the steering actuator's time constant nominal (30 ms), x3 (the robustness grid's
lag x3, 90 ms) and a slow servo (150 ms), each with a command dead time of 0 (the runner's
own timing, as Tables II-III), 10 ms (the order of the ECU's RX-to-TX latency, issue 37)
and 25 ms (one control period) (:class:`DeadTimePlant`). Reported: e_Y RMSE (cm) per run.

The settings are not tuned here: the weights stay those tuned without them, so a row shows
what switching a field on does to the shipped tuning, not what it could give once tuned
(turning one on by default belongs to the tuning procedure, docs/tuning.md).

Usage: ``python -m studies.delay_compensation --out DIR`` (writes delay_compensation.md
and .json).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from controller.base import Command, Controller, StepDebug, VehicleSample
from controller.dkmpc import Dkmpc
from controller.eso_dkmpc import EsoDkmpc
from controller.lmpc import Lmpc
from controller.reference import ReferencePath
from controller.tuning import MpcTuning, load_tuning
from hil.errors import HilError
from hil.scenario import load_scenario
from models.bicycle import LinearBicycle
from models.koopman import KoopmanModel
from models.vehicle_params import load_vehicle_params
from studies.closed_loop import CONTROL_PERIOD_MS, PLANT_PERIOD_MS, TICK_MS, run_closed_loop

SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
#: (label, steering time constant in s): nominal, the grid's lag x3, a slow servo.
LAGS: tuple[tuple[str, float], ...] = (("nominal", 0.03), ("lag x3", 0.09), ("slow servo", 0.15))
#: Command dead times of the plant (ms), multiples of the 5 ms tick.
DEAD_TIMES_MS = (0, 10, 25)
#: The fixed part of the delay where the plant has no dead time (s): a task time.
TASK_TIME_S = 0.005
SETTINGS = ("off", "rate rows", "delay comp.", "both")


class AgedSamples(Controller):
    """A controller whose samples carry their age at the task start as the runner's timing
    gives it: step k runs at t = 25 k ms on the newest sample the plant published every
    ``plant_period_ms``, so its age is (25 k mod plant period) ms (0 or 5 ms at 10 ms)."""

    def __init__(self, inner: Controller, plant_period_ms: int = PLANT_PERIOD_MS) -> None:
        self.inner, self.name = inner, inner.name
        self._plant_period_ms = plant_period_ms
        self._step = 0

    def set_path(self, path: ReferencePath) -> None:
        self.inner.set_path(path)

    def reset(self) -> None:
        self._step = 0
        self.inner.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        age_ms = (self._step * CONTROL_PERIOD_MS) % self._plant_period_ms
        self._step += 1
        return self.inner.step(dataclasses.replace(sample, sample_age_s=age_ms / 1000.0))


class DeadTimePlant:
    """A plant whose commands take effect ``dead_time_ms`` later (a FIFO of the runner's 5 ms
    ticks; the first commands before any arrives: the initial one, straight ahead)."""

    def __init__(self, plant: Any, dead_time_ms: int) -> None:
        if dead_time_ms % TICK_MS:
            raise ValueError(f"dead time {dead_time_ms} ms: not a multiple of the {TICK_MS} ms tick")
        self.plant, self._ticks = plant, dead_time_ms // TICK_MS
        self._queue: deque[Any] = deque()

    def reset(self, **start: float) -> None:
        self._queue.clear()
        self.plant.reset(**start)

    def outputs(self) -> Any:
        return self.plant.outputs()

    def true_outputs(self) -> Any:
        return self.plant.true_outputs()

    def step(self, command: Any, dt: float) -> None:
        self._queue.append(command)
        applied = self._queue.popleft() if len(self._queue) > self._ticks else type(command)(
            drive_torque=0.0, steer_angle=0.0)
        self.plant.step(applied, dt)


def builders() -> dict[str, tuple[Callable[[Any], Controller], MpcTuning]]:
    """Name -> (controller from a table, the tuning file's table)."""
    tuning = load_tuning()
    model = KoopmanModel.load()
    longitudinal = tuning.longitudinal
    return {"ESO-DKMPC": (lambda table: EsoDkmpc(model, table, longitudinal), tuning.eso_dkmpc),
            "DKMPC": (lambda table: Dkmpc(model, table, longitudinal), tuning.dkmpc),
            "LMPC": (lambda table: Lmpc(LinearBicycle(), table, longitudinal), tuning.lmpc)}


def setting_fields(setting: str, dead_time_ms: int, steer_rate_limit: float) -> dict[str, float]:
    """The two tuning fields of ``setting`` on a plant with ``dead_time_ms``."""
    fixed = dead_time_ms / 1000.0 if dead_time_ms else TASK_TIME_S
    return {"qp_steer_rate_limit": steer_rate_limit if setting in ("rate rows", "both") else 0.0,
            "delay_compensation_s": fixed if setting in ("delay comp.", "both") else 0.0}


def measure(build: Callable[[Any], Controller], table: MpcTuning, scenario_name: str, time_constant: float,
            dead_time_ms: int, fields: dict[str, float]) -> float:
    """e_Y RMSE (m) of one run; NaN when it did not complete."""
    scenario = load_scenario(scenario_name)
    plant = DeadTimePlant(scenario.vehicle(dataclasses.replace(scenario.vehicle_params(),
                                                               steer_time_constant=time_constant)), dead_time_ms)
    result = run_closed_loop(scenario, AgedSamples(build(dataclasses.replace(table, **fields))), plant=plant)
    return float(result.tracking.lateral.rmse) if result.completed else float("nan")


def run_study(on_run: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Every run as a record: controller, setting, scenario, lag, dead time, fields, e_Y RMSE (m)."""
    rate_limit = load_vehicle_params().steer_rate_limit
    records = []
    for name, (build, table) in builders().items():
        for setting in SETTINGS:
            for scenario in SCENARIOS:
                for lag, time_constant in LAGS:
                    for dead in DEAD_TIMES_MS:
                        fields = setting_fields(setting, dead, rate_limit)
                        rmse = measure(build, table, scenario, time_constant, dead, fields)
                        records.append({"controller": name, "setting": setting, "scenario": scenario, "lag": lag,
                                        "steer_time_constant_s": time_constant, "dead_time_ms": dead, **fields,
                                        "lateral_rmse_m": rmse})
                        if on_run is not None:
                            on_run(f"{name} {setting} {scenario} {lag} {dead} ms: {rmse * 100:.2f} cm")
    return records


def _cell(records: list[dict[str, Any]], **key: Any) -> float:
    (record,) = [r for r in records if all(r[k] == v for k, v in key.items())]
    return record["lateral_rmse_m"]


def report(records: list[dict[str, Any]]) -> str:
    """The markdown: per lane change a row per controller and setting, a column per plant."""
    columns = [(lag, dead) for lag, _ in LAGS for dead in DEAD_TIMES_MS]
    lines = ["# Steer-rate rows and delay compensation, measured", "",
             "Written by `make delay-compensation` (`python -m studies.delay_compensation`; the settings and "
             "plants in its docstring). Closed loop without CAN; the sample's age as the runner's timing "
             "gives it (0 or 5 ms). Each cell: e_Y RMSE (cm); '-' did not complete. Columns: the steering "
             "actuator (time constant 30 ms nominal, 90 ms lag x3, 150 ms slow servo) / the plant's command "
             "dead time (ms). `delay comp.`: `delay_compensation_s` = the dead time "
             f"({TASK_TIME_S * 1000:g} ms where there is none); `rate rows`: `qp_steer_rate_limit` = the "
             "plant's 1.0 rad/s.", "",
             "Not tuned: the weights are those tuned with both fields off; switching a field on by default "
             "belongs to the tuning procedure (docs/tuning.md).", ""]
    for scenario in SCENARIOS:
        lines += [f"## {scenario}", "",
                  "| controller | setting | " + " | ".join(f"{lag} / {dead}" for lag, dead in columns) + " |",
                  "|---|---|" + "---:|" * len(columns)]
        for name in builders_names(records):
            for setting in SETTINGS:
                values = [_cell(records, controller=name, setting=setting, scenario=scenario, lag=lag,
                                dead_time_ms=dead) for lag, dead in columns]
                shown = ["-" if np.isnan(v) else f"{v * 100:.2f}" for v in values]
                lines.append(f"| {name} | {setting} | " + " | ".join(shown) + " |")
        lines.append("")
    return "\n".join(lines)


def builders_names(records: list[dict[str, Any]]) -> list[str]:
    """The controllers of ``records`` in their order of appearance."""
    return list(dict.fromkeys(r["controller"] for r in records))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.delay_compensation",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for delay_compensation.md and .json")
    args = parser.parse_args(argv)
    if not args.out.is_dir():
        print(f"error: --out {args.out}: no such folder", file=sys.stderr)
        return 1
    try:
        records = run_study(on_run=lambda line: print(line, file=sys.stderr, flush=True))
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    text = report(records)
    (args.out / "delay_compensation.md").write_text(text, encoding="utf-8")
    (args.out / "delay_compensation.json").write_text(json.dumps({"runs": records}, indent=1) + "\n",
                                                      encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

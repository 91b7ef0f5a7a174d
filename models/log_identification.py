"""What ``python -m models.koopman_train --logs LOG [LOG ...] --out DIR`` writes besides the
Koopman artefact: the linear bicycle fitted to the same data and the report of prediction
errors on the held-out pieces (issue 20; docs/identification.md). numpy only: the torch
training stays in ``models/koopman_train.py``.

``DIR`` receives ``koopman.npz`` + ``koopman.json`` (the artefact, of the committed
artefact's form), ``bicycle.json`` (``models.bicycle_fit``), ``report.md`` and
``report.json``: Table I's figures (one-step max / avg / RMSE and the 1 s open-loop RMSE
of vx, vy and yaw rate, ``models.koopman_metrics.prediction_errors``) on the pieces the
training held out as its test split, for the new Koopman model, the fitted bicycle, the
nominal bicycle and, where its states match the data, the committed default artefact.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from models.bicycle import LinearBicycle
from models.bicycle_fit import BicycleFitError, FittedBicyclePredictor, fit_bicycle, save_bicycle
from models.koopman import DEFAULT_ARTIFACT, KoopmanError, KoopmanModel
from models.koopman_metrics import OPEN_LOOP_STEPS, Trajectory, prediction_errors

VEHICLE_STATES = ("vx", "vy", "yaw_rate")
FIGURES = ("one_step_max", "one_step_avg", "one_step_rmse", "open_loop_rmse")


class _VehicleStates:
    """A predictor restricted to its own leading states; returns vx, vy, yaw rate."""

    def __init__(self, predictor: Any, n_states: int) -> None:
        self.predictor, self.n_states = predictor, n_states

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """x0 (batch, >= n_states), inputs (batch, n, 2) -> (batch, n, 3)."""
        return self.predictor.predict(x0[:, : self.n_states], inputs)[..., :3]


def compare_models(test_runs: Sequence[Trajectory], new_model: KoopmanModel,
                   bicycle: LinearBicycle | None, ts: float) -> dict[str, dict[str, dict[str, float]]]:
    """Table I figures of each model on ``test_runs``: {model: {state: {figure: value}}}.

    The bicycles (fitted, nominal) and the committed artefact join only where the data
    are vehicle data ([vx, vy, yaw_rate] states, a ``steer`` input); a model for study
    (other states or inputs) is reported alone, on all its states.
    """
    states, inputs = tuple(test_runs[0].state_names), tuple(test_runs[0].input_names)
    if states[:3] != VEHICLE_STATES or "steer" not in inputs:
        figures = prediction_errors(new_model, test_runs, OPEN_LOOP_STEPS)
        return {"Koopman, identified from the data": figures}
    models: dict[str, Any] = {"Koopman, identified from the logs": _VehicleStates(new_model, new_model.n_x)}
    steer = inputs.index("steer")
    if bicycle is not None:
        models["linear bicycle, fitted to the logs"] = FittedBicyclePredictor(bicycle, ts, steer)
    models["linear bicycle, nominal"] = FittedBicyclePredictor(LinearBicycle(), ts, steer)
    try:
        default = KoopmanModel.load(DEFAULT_ARTIFACT)
    except KoopmanError:
        default = None
    if default is not None and tuple(default.state_names) == states[: default.n_x] \
            and tuple(default.input_names) == inputs:
        models["Koopman, committed default (dk_d5)"] = _VehicleStates(default, default.n_x)
    full = {name: prediction_errors(_Padded(model, len(states)), test_runs, OPEN_LOOP_STEPS)
            for name, model in models.items()}
    return {name: {s: figures[s] for s in VEHICLE_STATES} for name, figures in full.items()}


class _Padded:
    """A vehicle-state predictor padded to the data's states (extra states predicted as
    NaN-free zeros and left out of the report)."""

    def __init__(self, predictor: Any, n_states: int) -> None:
        self.predictor, self.n_states = predictor, n_states

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        vehicle = self.predictor.predict(x0, inputs)
        out = np.zeros(vehicle.shape[:2] + (self.n_states,))
        out[..., :3] = vehicle
        return out


def load_log_runs(files: Sequence[Path], ts: float, input_source: str, mapping: Path | None,
                  dbc: Path | None) -> tuple[list[Trajectory], dict[str, Any], list[str], float]:
    """(runs, metadata, warnings, Ts) of ``--logs``: CAN logs, or named-column CSV files
    with ``mapping`` (then Ts is the mapping's). Warnings are printed to stderr too.

    Raises:
        LogDataError: see ``models.can_log_data`` and ``models.named_csv_data``.
    """
    from models.can_log_data import LogDataError, csv_header, is_python_can_csv, load_logs

    named = [Path(f) for f in files if Path(f).suffix.lower() == ".csv" and Path(f).is_file()
             and not is_python_can_csv(Path(f))]
    if named and mapping is None:
        raise LogDataError(f"{named[0]}: a named-column CSV (header {csv_header(named[0])[:60]!r}), not a "
                           "python-can CSV log: give --mapping MAP.toml (docs/identification.md)")
    if mapping is not None:
        from models.named_csv_data import load_mapping, load_named_csv

        if len(named) != len(files):
            others = [str(f) for f in files if Path(f) not in named]
            raise LogDataError(f"--mapping is for named-column CSV files only; not one: {', '.join(others)}")
        parsed = load_mapping(mapping)
        runs = load_named_csv(files, parsed)
        meta = {"data_source": "named_csv", "logs": [str(f) for f in files], "mapping": str(mapping),
                "data_seconds": round(sum(len(r) for r in runs) * parsed.sample_time_s, 3),
                "n_runs": len(runs), "input_source": "mapping"}
        return runs, meta, [], parsed.sample_time_s
    dataset = load_logs(files, ts, input_source, dbc)
    for line in dataset.warnings:
        print(f"warning: {line}", file=sys.stderr)
    return dataset.trajectories, dataset.metadata(), dataset.warnings, ts


def write_log_products(out_dir: Path, model: KoopmanModel, runs: Sequence[Trajectory],
                       test_names: Sequence[str], ts: float, vehicle_file: Path | None,
                       data_metadata: dict[str, Any], warnings: Sequence[str]) -> list[Path]:
    """Fit the bicycle to the training pieces, write ``bicycle.json``, and the report of
    every model on the held-out pieces ``test_names``; returns the files written."""
    test_runs = [r for r in runs if r.name in set(test_names)]
    fit_runs = [r for r in runs if r.name not in set(test_names)]
    written: list[Path] = []
    bicycle = None
    fit_note = ""
    try:
        fit = fit_bicycle(fit_runs, ts, vehicle_file)
        bicycle = LinearBicycle(fit.params)
        written.append(save_bicycle(out_dir / "bicycle.json", fit, {
            "logs": data_metadata.get("logs", []), "vehicle_file": str(vehicle_file or "models/vehicle.toml"),
            "pieces": [r.name for r in fit_runs]}))
    except BicycleFitError as error:
        fit_note = f"no bicycle fitted: {error}"
    errors = compare_models(test_runs, model, bicycle, ts)
    report = {"data": data_metadata, "warnings": list(warnings), "test_pieces": list(test_names),
              "test_seconds": round(sum(len(r) for r in test_runs) * ts, 2),
              "open_loop_steps": OPEN_LOOP_STEPS, "prediction_errors": errors,
              "bicycle": json.loads((out_dir / "bicycle.json").read_text()) if bicycle else fit_note}
    json_path = out_dir / "report.json"
    json_path.write_text(json.dumps(report, indent=1) + "\n")
    md_path = out_dir / "report.md"
    md_path.write_text(report_markdown(report))
    return [*written, json_path, md_path]


def report_markdown(report: dict[str, Any]) -> str:
    """The report as a page: data, bicycle, Table I figures per model."""
    data = report["data"]
    lines = ["# Identification from CAN logs", "",
             f"Logs: {', '.join(data.get('logs', []))}; inputs from the "
             f"{data.get('input_source', 'command')}s; {data.get('data_seconds', 0):.0f} s of usable data "
             f"in {data.get('n_runs', 0)} pieces. Held-out test pieces: {len(report['test_pieces'])} "
             f"({report['test_seconds']:.0f} s).", ""]
    if report["warnings"]:
        lines += ["Warnings:", "", *[f"- {w}" for w in report["warnings"]], ""]
    bicycle = report["bicycle"]
    if isinstance(bicycle, dict):
        lines += ["Fitted bicycle: "
                  f"Cf {bicycle['cornering_stiffness_front']:.0f} N/rad, Cr {bicycle['cornering_stiffness_rear']:.0f} "
                  f"N/rad, Iz {bicycle['yaw_inertia']:.0f} kg m^2 (mass {bicycle['mass']:.0f} kg, lf {bicycle['lf']} m, "
                  f"lr {bicycle['lr']} m from the vehicle file; {bicycle['fit']['samples_used']} samples).", ""]
    else:
        lines += [bicycle, ""]
    lines += [f"Prediction errors on the held-out pieces (one step, and RMSE over "
              f"{report['open_loop_steps']} open-loop steps with the recorded inputs):", "",
              "| model | state | one-step max | one-step avg | one-step RMSE | open-loop RMSE |",
              "|---|---|---|---|---|---|"]
    for name, per_state in report["prediction_errors"].items():
        for state, figures in per_state.items():
            lines.append(f"| {name} | {state} | " + " | ".join(f"{figures[f]:.4f}" for f in FIGURES) + " |")
    return "\n".join(lines) + "\n"

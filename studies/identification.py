"""Identification of our plant from its own CAN logs (issue 20).

Part 1, the identification drive: a closed circuit driven for 10 minutes with speed steps
over 3-30 m/s (``hil/paths/identification.csv``, ``hil/scenarios/identification/drive.toml``),
written by ``python -m studies.identification drive``; a test checks that the shipped
files equal the regenerated ones.

The circuit is the polar curve r(theta) = R0 (1 + 0.2 sin 2 theta + 0.08 cos 3 theta),
R0 = 420 m: 2.78 km a lap, left and right bends, the tightest of radius 248 m (3.6 m/s^2
at 30 m/s, inside the grip of mu >= 0.5 with the excitation on top), laid out four times
in driving order, each lap 3 % (9 to 16 m) wider than the one before so that the laps
never coincide (11.5 km, more than the 10-minute drive covers). The speed holds each of
20 levels for 22 s and ramps between them at 1.5 m/s^2; the levels visit 3-30 m/s in a
mixed order so that every speed is reached from below and from above.

Part 2, the study (``python -m studies.identification study``, ``make identify``): a
changed plant (mass +300 kg, rear tyres with 20 % less cornering stiffness, steering
actuator lag x3) drives the identification drive over CAN with LMPC and the
``prbs-torque`` excitation while the bus is recorded; the Koopman model and the linear
bicycle are identified from that log alone (``python -m models.koopman_train --logs``);
then Tables II and III run on the changed plant with the nominal and the re-identified
models, for ESO-DKMPC, DKMPC and LMPC alike, and NMPC with its nominal single track, beside
the nominal plant with the nominal models. The steering servo's time constant is fitted from
the same log (``models.servo_fit``); ESO-DKMPC, DKMPC and LMPC run once more with their
nominal models and only ``delay_compensation_s`` set to how much slower the servo is than
the nominal one (the calibration a new vehicle needs before a new model).
The fitted bicycle is compared with the nominal one and with the changed plant's own
flat-track stiffnesses at its static loads (the extra mass moves the tyres along their
degressive load curve, so the axles' stiffness changes are not exactly 0 % and -20 %).

Writes to ``--out`` (default ``results/identification``): ``tables.md`` (Tables II and
III), ``summary.json`` (every figure, the fitted bicycle against the nominal one),
``logs/identification_timing.json`` (stage and run wall times, the machine; not under
version control) and ``training_report.md`` (the training's prediction errors on held-out
pieces of the drive). The log and the models stay in ``--work`` (``build/identification``).
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from hil.path_files import PATH_DIR, write_path_csv
from hil.scenario import SCENARIO_DIR

#: The machine's part of the study (stage and run wall times, the host), under ``--out``/logs/.
TIMING_FILE = "identification_timing.json"
#: The repository: the training command runs with it on the module path.
REPO = Path(__file__).resolve().parent.parent
IDENTIFICATION_PATH_FILE = PATH_DIR / "identification.csv"
#: In a folder of its own: the shipped scenarios of hil/scenarios/*.toml are the double
#: lane changes of the evaluation (tests/test_scenario.py).
IDENTIFICATION_SCENARIO_FILE = SCENARIO_DIR / "identification" / "drive.toml"
CIRCUIT_RADIUS_M = 420.0
CIRCUIT_SHAPE = (0.2, 0.08)  # amplitudes of sin 2 theta and cos 3 theta
CIRCUIT_LAPS = 4
LAP_GROWTH = 0.03
POINT_SPACING_M = 0.45  # chords of 0.45 m of arc stay inside the contract's 0.5 m
#: Speed levels (m/s), each held for LEVEL_HOLD_S, ramps of SPEED_RAMP_MPS2 between them.
SPEED_LEVELS_MPS = (8.0, 15.0, 5.0, 22.0, 12.0, 28.0, 3.0, 18.0, 25.0, 10.0,
                    30.0, 6.0, 20.0, 14.0, 26.0, 4.0, 16.0, 24.0, 9.0, 12.0)
LEVEL_HOLD_S = 22.0
SPEED_RAMP_MPS2 = 1.5
DRIVE_MU = 0.85


def _circuit_radius(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radius (m) and its derivative d r / d theta of the widening circuit at ``theta``
    (rad, from 0 over all laps)."""
    a, b = CIRCUIT_SHAPE
    shape = 1.0 + a * np.sin(2.0 * theta) + b * np.cos(3.0 * theta)
    d_shape = 2.0 * a * np.cos(2.0 * theta) - 3.0 * b * np.sin(3.0 * theta)
    growth = 1.0 + LAP_GROWTH * theta / (2.0 * math.pi)
    radius = CIRCUIT_RADIUS_M * growth * shape
    return radius, CIRCUIT_RADIUS_M * (LAP_GROWTH / (2.0 * math.pi) * shape + growth * d_shape)


def circuit_points(laps: int = CIRCUIT_LAPS, spacing_m: float = POINT_SPACING_M) -> np.ndarray:
    """The circuit, ``laps`` times in driving order (counter-clockwise), points
    ``spacing_m`` of arc apart: (n, 3) [x, y, yaw], starting at the origin.

    Each lap is LAP_GROWTH (3 %, 9 to 16 m) wider than the one before: laps that lay on
    top of each other would make the nearest point of the path ambiguous, and a
    controller that engages with a search over the whole path could start on a later lap
    and run out of path early (it did, 540 s into the drive, before the laps widened).
    """
    theta = np.linspace(0.0, 2.0 * math.pi * laps, 400_000 * laps + 1)
    radius, _ = _circuit_radius(theta)
    x, y = radius * np.cos(theta), radius * np.sin(theta)
    arc = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    s = np.arange(0.0, arc[-1], spacing_m)
    theta_s = np.interp(s, arc, theta)
    r, dr = _circuit_radius(theta_s)
    px, py = r * np.cos(theta_s), r * np.sin(theta_s)
    tangent_x = dr * np.cos(theta_s) - r * np.sin(theta_s)
    tangent_y = dr * np.sin(theta_s) + r * np.cos(theta_s)
    yaw = np.arctan2(tangent_y, tangent_x)
    return np.column_stack([px - px[0], py - py[0], yaw])  # start at the origin


def speed_breakpoints() -> tuple[list[float], list[float]]:
    """Piecewise-linear target speed: (times s, speeds m/s) of the 10-minute drive."""
    times, speeds = [0.0], [SPEED_LEVELS_MPS[0]]
    for level in SPEED_LEVELS_MPS[1:]:
        hold_end = times[-1] + LEVEL_HOLD_S
        times.append(hold_end)
        speeds.append(speeds[-1])
        times.append(hold_end + abs(level - speeds[-1]) / SPEED_RAMP_MPS2)
        speeds.append(level)
    times.append(times[-1] + LEVEL_HOLD_S)
    speeds.append(speeds[-1])
    return times, speeds


def scenario_text(duration_s: float, start_yaw_rad: float) -> str:
    """The scenario TOML of the identification drive."""
    times, speeds = speed_breakpoints()
    kmh = [round(v * 3.6, 3) for v in speeds]
    return "\n".join([
        "# Identification drive (issue 20, docs/identification.md): the closed circuit of",
        "# studies/identification.py, 20 speed levels over 3-30 m/s held 22 s each with 1.5 m/s^2",
        "# ramps. Drive it with an excitation and record the bus, e.g.",
        "#   python -m hil run --scenario hil/scenarios/identification/drive.toml --controller lmpc \\",
        "#       --excite prbs-torque --log id.log",
        "# Written by `python -m studies.identification drive`; do not edit by hand.",
        'name = "identification"',
        f'description = "Identification drive: circuit, speed steps 3-30 m/s, {duration_s / 60:.0f} min, '
        f'mu = {DRIVE_MU}"',
        f"duration_s = {duration_s}",
        "",
        "[path]",
        "id = 1",
        'file = "../../paths/identification.csv"',
        "",
        "[road]",
        f"mu = {DRIVE_MU}",
        "",
        "[vehicle]",
        "mass_offset_kg = 0.0",
        "",
        "[start]",
        "x_m = 0.0",
        "y_m = 0.0",
        f"yaw_rad = {start_yaw_rad:.6f}",
        f"speed_kmh = {kmh[0]}",
        "",
        "[speed_profile]",
        f"time_s = {[round(t, 3) for t in times]}",
        f"target_speed_kmh = {kmh}",
        "",
    ])


def write_drive(path_file: Path = IDENTIFICATION_PATH_FILE,
                scenario_file: Path = IDENTIFICATION_SCENARIO_FILE) -> tuple[Path, Path]:
    """Write the circuit CSV and the scenario TOML (the shipped files by default)."""
    points = circuit_points()
    scenario_file.parent.mkdir(exist_ok=True)
    write_path_csv(path_file, points)
    times, _ = speed_breakpoints()
    scenario_file.write_text(scenario_text(round(times[-1], 3), float(points[0, 2])), encoding="ascii")
    return path_file, scenario_file


# ---------------------------------------------------------------- the study
#: The changed plant: mass offset (kg), the factor on the rear tyres' cornering stiffness
#: and the factor on the steering actuator's lag.
CHANGED_MASS_OFFSET_KG = 300.0
CHANGED_REAR_STIFFNESS_SCALE = 0.8
CHANGED_LAG_FACTOR = 3.0
#: The row kind of :func:`table_runs` for a nominal model with the servo's delay compensation.
CALIBRATED = "calibrated"
#: The drive's controller. Not one with an observer: the excitation is not in the
#: command the observer sees, so it estimates it as a disturbance and fights it (DMDc-ESO
#: on the changed plant then kept the steering saturated at +-0.3 rad from 20 s on).
DRIVE_CONTROLLER = "lmpc"
DRIVE_EXCITATION = "prbs-torque"
TABLE_SCENARIOS = {"dlc_high_mu": "Table II (high mu), changed plant",
                   "dlc_low_mu": "Table III (low mu), changed plant"}


def changed_params(params: Any) -> Any:
    """``VehicleParams`` of the changed plant from a scenario's (mass +300 kg, rear tyres'
    cornering stiffness x0.8, lag x3)."""
    return dataclasses.replace(
        params, mass=params.mass + CHANGED_MASS_OFFSET_KG,
        cornering_stiffness_rear_scale=params.cornering_stiffness_rear_scale * CHANGED_REAR_STIFFNESS_SCALE,
        steer_time_constant=params.steer_time_constant * CHANGED_LAG_FACTOR)


def record_drive(log: Path) -> dict[str, Any]:
    """The identification drive on the changed plant over CAN (virtual bus, lockstep),
    LMPC with the excitation, every frame recorded to ``log``."""
    from hil.faults import FaultSpec, VehicleFaults
    from hil.scenario import load_scenario
    from models.vehicle_params import load_vehicle_params

    nominal_lag = load_vehicle_params().steer_time_constant
    # The HIL's vehicle faults change the plant: mass offset, rear tyres, extra actuator lag.
    spec = FaultSpec(vehicle=VehicleFaults(mass_offset_kg=CHANGED_MASS_OFFSET_KG,
                                           steer_extra_lag_s=(CHANGED_LAG_FACTOR - 1.0) * nominal_lag,
                                           cornering_stiffness_rear_scale=CHANGED_REAR_STIFFNESS_SCALE))
    return drive_over_can(load_scenario(IDENTIFICATION_SCENARIO_FILE), log, spec)


def drive_over_can(scenario: Any, log: Path, faults: Any = None) -> dict[str, Any]:
    """Drive ``scenario`` (``hil.scenario.Scenario``, e.g. the identification drive) over
    CAN (virtual bus, lockstep) with LMPC and the excitation, every frame recorded to
    ``log``; ``faults`` (``hil.faults.FaultSpec``) change the plant. Returns the drive's
    facts (frames, active cycles, tracking, the log's SHA-256)."""
    from hil.session import default_options, run_hil

    options = dataclasses.replace(default_options(DRIVE_CONTROLLER, log_path=log), faults=faults,
                                  excite=DRIVE_EXCITATION)
    result = run_hil(scenario, options)
    summary = result.summary()
    return {"controller": DRIVE_CONTROLLER, "excitation": DRIVE_EXCITATION,
            "frames_logged": summary["frames_logged"], "active_cycles": summary["active_cycles"],
            "tracking": summary["tracking"],
            "log_sha256": hashlib.sha256(log.read_bytes()).hexdigest()}


def weighed_vehicle_file(work: Path) -> Path:
    """The vehicle file an owner of the changed plant would write: the nominal file with
    the mass weighed (+300 kg); the tyres are not measured (no rear factor in it). The
    bicycle takes mass and geometry from it; the fit finds the tyres and the inertia."""
    from models.vehicle_params import load_vehicle_params

    mass = load_vehicle_params().mass + CHANGED_MASS_OFFSET_KG
    return measured_vehicle_file(work / "vehicle_changed.toml", {"mass": mass})


def measured_vehicle_file(out: Path, measured: dict[str, float]) -> Path:
    """Write ``out``: the nominal vehicle file with the ``measured`` values (field ->
    value, e.g. the weighed mass) in place of the nominal ones, every other line as it is."""
    from models.vehicle_params import DEFAULT_PARAMS_PATH, load_vehicle_params, params_as_dict

    lines = [f"{key} = {measured[key]!r}" if (key := line.split("=")[0].strip()) in measured else line
             for line in DEFAULT_PARAMS_PATH.read_text().splitlines()]
    out.write_text("\n".join(lines) + "\n")
    written = params_as_dict(load_vehicle_params(out))
    missing = sorted(key for key, value in measured.items() if written.get(key) != value)
    if missing:
        raise SystemExit(f"error: {out}: the line(s) of {', '.join(missing)} of {DEFAULT_PARAMS_PATH} "
                         "were not found")
    return out


def identify(log: Path, model_dir: Path, epochs: int | None, vehicle_file: Path,
             options: Sequence[str] = ()) -> None:
    """``python -m models.koopman_train --logs LOG --out DIR --replace --vehicle FILE [OPTIONS]``
    as its own process, the command a user runs (the study owns DIR) (``options``: more
    training options, e.g. ``--steps-per-epoch 5``). Raises SystemExit when it fails."""
    argv = ["--logs", str(log), "--out", str(model_dir), "--replace", "--no-progress", "--vehicle",
            str(vehicle_file)]
    if epochs is not None:
        argv += ["--epochs", str(epochs)]
    argv += list(options)
    # the repository first on the path, whatever the working folder (paths stay relative to it)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, "-m", "models.koopman_train", *argv], env=env)
    if done.returncode != 0:
        raise SystemExit(f"error: training from {log} failed (exit status {done.returncode})")


def servo_calibration(log: Path) -> dict[str, Any]:
    """The steering servo's time constant fitted from the drive's log (``models.servo_fit``:
    command against measured wheel angle), the nominal one the models were trained on
    (models/vehicle.toml) and the delay compensation their difference gives
    (``MpcTuning.delay_compensation_s``, 0 when the servo is not slower than nominal)."""
    from models.can_log_data import load_logs
    from models.servo_fit import fit_servo_lag
    from models.vehicle_params import load_vehicle_params

    nominal = load_vehicle_params()
    data = load_logs([log])
    runs = [(t.inputs[:, t.input_names.index("steer")], t.states[:, t.state_names.index("steer_measured")])
            for t in data.trajectories]
    fit = fit_servo_lag(runs, data.ts, rate_limit=nominal.steer_rate_limit)
    delay = max(0.0, fit.time_constant_s - nominal.steer_time_constant)
    # rounded to the millisecond: a calibration value as a person would write it in a tuning file
    return {"time_constant_s": round(fit.time_constant_s, 5), "nominal_time_constant_s": nominal.steer_time_constant,
            "delay_compensation_s": round(delay, 3), "steps": fit.steps,
            "one_step_rmse_rad": round(fit.one_step_rmse_rad, 7)}


def table_runs(model_dir: Path, delay_compensation_s: float) -> list[dict[str, Any]]:
    """Tables II and III: per scenario, the nominal plant with the nominal models, then the
    changed plant with the nominal and the identified models (ESO-DKMPC, DKMPC, LMPC) and
    NMPC with its nominal model; and ESO-DKMPC, DKMPC and LMPC with their nominal models and
    ``delay_compensation_s`` (the servo calibrated from the log, :func:`servo_calibration`)."""
    from controller.registry import create_controller
    from controller.tuning import load_tuning
    from hil.scenario import load_scenario
    from models.vehicle import FourWheelVehicle, VehicleCommand
    from studies.campaign.tuning_override import build_controller, with_override
    from studies.closed_loop import run_closed_loop
    from studies.paper_tables import run_summary

    def calibrated(controller: str) -> Any:
        override = {"delay_compensation_s": delay_compensation_s}
        return build_controller(controller, with_override(load_tuning(), controller, override))

    # DKMPC (the same model without the observer) and NMPC (the nominal single track) on the
    # changed plant say whether a failure of ESO-DKMPC with the nominal model is the
    # observer's or every nominal-model MPC's.
    variants = [("nominal", "eso-dkmpc", None), ("nominal", "lmpc", None),
                ("changed", "eso-dkmpc", None), ("changed", "eso-dkmpc", model_dir / "koopman"),
                ("changed", "dkmpc", None), ("changed", "dkmpc", model_dir / "koopman"),
                ("changed", "lmpc", None), ("changed", "lmpc", model_dir / "bicycle.json"),
                ("changed", "nmpc", None)]
    # The nominal models told only how much later the slower servo acts: no new model.
    variants += [("changed", name, CALIBRATED) for name in ("eso-dkmpc", "dkmpc", "lmpc")]
    runs = []
    for name in TABLE_SCENARIOS:
        scenario = load_scenario(name)
        for plant_kind, controller, model in variants:
            params = scenario.vehicle_params()
            if plant_kind == "changed":
                params = changed_params(params)
            started = time.perf_counter()
            law = calibrated(controller) if model == CALIBRATED else create_controller(controller, model_path=model)
            result = run_closed_loop(scenario, law, plant=FourWheelVehicle(params), command_type=VehicleCommand)
            summary = run_summary(result)
            kind = "calibrated" if model == CALIBRATED else "identified" if model else "nominal"
            summary.update(plant=plant_kind, model=kind,
                           controller=_label(plant_kind, controller, kind, delay_compensation_s),
                           law=controller, seconds=round(time.perf_counter() - started, 2))
            runs.append(summary)
            print(f"{name}: {summary['controller']}: e_Y RMSE "
                  f"{summary['tracking']['lateral_error_m']['rmse']:.4f} m", flush=True)
    return runs


def _label(plant_kind: str, controller: str, kind: str, delay_compensation_s: float) -> str:
    """A table row's name; ``kind``: "nominal", "identified" or "calibrated" (nominal model,
    delay compensation from the servo fit)."""
    law = {"eso-dkmpc": "ESO-DKMPC", "dkmpc": "DKMPC", "lmpc": "LMPC", "nmpc": "NMPC"}[controller]
    koopman = controller in ("eso-dkmpc", "dkmpc")
    if controller == "nmpc":
        model = "nominal single track"
    elif kind == "identified":
        model = "identified Koopman" if koopman else "fitted bicycle"
    else:
        model = "nominal Koopman (dk_d5)" if koopman else "nominal bicycle"
    if kind == "calibrated":
        model += f" + delay compensation {1000 * delay_compensation_s:.0f} ms from the servo fit"
    return f"{law}, {model}, {plant_kind} plant"


def bicycle_comparison(model_dir: Path, plant_params: Any = None) -> dict[str, Any]:
    """The fitted bicycle's parameters against the nominal ones and the plant's own (the
    stiffnesses: the flat-track slope at the plant's static loads,
    ``models.bicycle.nominal_model_params``; the mass: the vehicle file's, as given to the
    fit). The plant (``VehicleParams``) is the changed plant unless ``plant_params`` is
    given; its figures are under ``changed_plant``."""
    from models.bicycle import nominal_model_params
    from models.vehicle_params import load_vehicle_params

    fitted = json.loads((model_dir / "bicycle.json").read_text())
    nominal = nominal_model_params()
    plant = nominal_model_params(plant_params if plant_params is not None
                                 else changed_params(load_vehicle_params()))

    def percent(value: float, reference: float) -> float:
        return round(100.0 * (value / reference - 1.0), 2)

    return {name: {"nominal": getattr(nominal, name), "changed_plant": getattr(plant, name),
                   "fitted": fitted[name],
                   "plant_change_percent": percent(getattr(plant, name), getattr(nominal, name)),
                   "change_percent": percent(fitted[name], getattr(nominal, name)),
                   "fit_error_percent": percent(fitted[name], getattr(plant, name))}
            for name in ("mass", "cornering_stiffness_front", "cornering_stiffness_rear", "yaw_inertia")}


def tables_markdown(runs: Sequence[dict[str, Any]], summary: dict[str, Any]) -> str:
    """Tables II and III of the changed plant, with what was identified and the times."""
    from studies.report import display_name, tracking_table

    bicycle = summary["bicycle"]
    lines = ["# Identification of a changed plant from its own CAN log", "",
             f"Changed plant: mass +{CHANGED_MASS_OFFSET_KG:.0f} kg, rear tyres' cornering stiffness "
             f"x{CHANGED_REAR_STIFFNESS_SCALE:g}, steering actuator lag x{CHANGED_LAG_FACTOR:g}. "
             f"Identification drive: {display_name(summary['drive']['controller'])} with the "
             f"`{summary['drive']['excitation']}` excitation on `hil/scenarios/identification/drive.toml` "
             f"(612 s, 3-30 m/s), {summary['drive']['frames_logged']} frames recorded; models identified "
             "from that log alone (`python -m models.koopman_train --logs`).", "",
             "Fitted bicycle against the nominal one and the changed plant's own (mass and "
             "geometry from the vehicle file: models/vehicle.toml with the changed plant's weighed "
             "mass; the plant's yaw inertia and front tyres are the nominal ones, its rear tyres "
             f"x{CHANGED_REAR_STIFFNESS_SCALE:g}, its steering lags x{CHANGED_LAG_FACTOR:g}, the fit "
             "uses the measured wheel angle). 'Changed plant' stiffnesses are the flat-track slopes "
             "of its tyres at its static loads (the extra mass moves them along the degressive load "
             "curve):", "",
             "| parameter | nominal | changed plant | fitted | plant vs nominal | fitted vs nominal "
             "| fitted vs plant |", "|---|---|---|---|---|---|---|"]
    for name, row in bicycle.items():
        lines.append(f"| {name} | {row['nominal']:.0f} | {row['changed_plant']:.0f} | {row['fitted']:.0f} "
                     f"| {row['plant_change_percent']:+.1f} % | {row['change_percent']:+.1f} % "
                     f"| {row['fit_error_percent']:+.1f} % |")
    servo = summary["servo"]
    lines += ["", f"Steering servo fitted from the same log (`models.servo_fit`: a first-order lag of the "
              f"measured wheel angle behind the command, {servo['steps']} steps, one-step RMSE "
              f"{servo['one_step_rmse_rad']:.1e} rad): time constant {1000 * servo['time_constant_s']:.1f} ms "
              f"against the nominal {1000 * servo['nominal_time_constant_s']:.0f} ms the models were trained "
              f"on. The rows 'delay compensation' keep the nominal models and set only "
              f"`delay_compensation_s` = {1000 * servo['delay_compensation_s']:.0f} ms, the difference "
              "(docs/tuning.md, 'Actuator terms'); every other tuning value is the file's."]
    lines.append("")
    for scenario, title in TABLE_SCENARIOS.items():
        lines.append(tracking_table(title, [r for r in runs if r["scenario"] == scenario], scenario))
    lines += ["", f"Stage times (drive over CAN, training, tables) and the machine: logs/{TIMING_FILE} "
                  "beside this file, not under version control.", ""]
    return "\n".join(lines)


def run_study(out: Path, work: Path, epochs: int | None, reuse_log: bool) -> list[Path]:
    """The whole study (see the module docstring); returns the files written."""
    from studies.machine import machine_description
    from studies.machine_figures import split_machine_keys

    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    log = work / "drive_changed.log"
    started = time.perf_counter()
    if reuse_log and log.is_file() and (work / "drive.json").is_file():
        drive = json.loads((work / "drive.json").read_text())
    else:
        log.unlink(missing_ok=True)
        drive = record_drive(log)
        drive["seconds"] = round(time.perf_counter() - started, 1)
        (work / "drive.json").write_text(json.dumps(drive, indent=1))
    seconds["drive"] = drive.get("seconds", math.nan)  # the recording's, also when reused
    started = time.perf_counter()
    model_dir = work / "model"
    identify(log, model_dir, epochs, weighed_vehicle_file(work))
    seconds["training"] = time.perf_counter() - started
    started = time.perf_counter()
    servo = servo_calibration(log)
    runs = table_runs(model_dir, servo["delay_compensation_s"])
    seconds["tables"] = time.perf_counter() - started
    # what the inputs decide is committed; the machine's part (wall times) goes to logs/
    runs_inputs_only, runs_timing = split_machine_keys(runs)
    summary = {"changed_plant": {"mass_offset_kg": CHANGED_MASS_OFFSET_KG, "lag_factor": CHANGED_LAG_FACTOR,
                                 "rear_cornering_stiffness_scale": CHANGED_REAR_STIFFNESS_SCALE},
               "drive": {k: v for k, v in drive.items() if k != "seconds"},
               "bicycle": bicycle_comparison(model_dir), "servo": servo, "runs": runs_inputs_only,
               "epochs": epochs}
    timing = {"machine": machine_description(), "seconds": {k: round(v, 1) for k, v in seconds.items()},
              "runs": runs_timing}
    written = [out / "tables.md", out / "summary.json", out / "training_report.md"]
    written[0].write_text(tables_markdown(runs_inputs_only, summary))
    written[1].write_text(json.dumps(summary, indent=1) + "\n")
    shutil.copyfile(model_dir / "report.md", written[2])
    (out / "logs").mkdir(exist_ok=True)
    (out / "logs" / TIMING_FILE).write_text(json.dumps(timing, indent=1) + "\n")
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``drive`` writes the identification drive's path and scenario; ``study`` runs
    the identification study."""
    parser = argparse.ArgumentParser(prog="python -m studies.identification", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("drive", help="write hil/paths/identification.csv and "
                                      "hil/scenarios/identification/drive.toml")
    study = commands.add_parser("study", help="identify the changed plant and run Tables II/III")
    study.add_argument("--out", type=Path, default=Path("results/identification"))
    study.add_argument("--work", type=Path, default=Path("build/identification"),
                       help="folder of the drive's log and the identified models")
    study.add_argument("--epochs", type=int, default=None, help="training epochs (default: the training's)")
    study.add_argument("--reuse-log", action="store_true",
                       help="train from the drive log already in --work (skips the 612 s drive)")
    args = parser.parse_args(argv)
    if args.command == "drive":
        for file in write_drive():
            print(f"wrote {file}")
        return 0
    for file in run_study(args.out, args.work, args.epochs, args.reuse_log):
        print(f"wrote {file}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

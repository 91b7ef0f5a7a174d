"""Vehicle variants the learned model never saw (issue 35 item 4, ``make vehicle-variants``).

For the nominal sedan (reference: stage 1 only), then each variant of
``models/vehicle_variants.toml`` (``--variants``, default all), selected on the scenarios
as their ``[vehicle] variant`` selects it:

1. Nominal models: the paper's lane changes at high friction (``dlc_high_mu``, 35 km/h,
   mu 0.85) and low friction (``dlc_low_mu``, 45-55 km/h, mu 0.5) with ESO-DKMPC, DKMPC,
   LMPC, NMPC and the registry's geometric baselines (Stanley), every controller with the
   models of the nominal sedan, in the closed-loop runner without CAN (``studies.closed_loop``,
   the HIL's timing), as ``make identify`` runs its tables.
2. Identification as ``make identify`` does it for its changed plant
   (``studies.identification``): the identification drive over CAN with LMPC and the
   ``prbs-torque`` excitation on the variant, the bus recorded; ``models.koopman_train
   --logs`` on that log alone, with a vehicle file holding what an owner measures of the
   car (its weighed mass and axle positions ``MEASURED_FIELDS``; tyres and inertia are left
   to the fit).
3. Identified models: ESO-DKMPC and DKMPC on the identified Koopman model, LMPC on the
   fitted bicycle, on the same two lane changes.

Each variant's results are kept in ``--work``/VARIANT/result.json (with its drive log and
models), so ``--reuse-results`` resumes an interrupted study; ``--reuse-log`` trains again
from the drive already recorded. The report (``studies.vehicle_variants_report``) goes to
``--out``: ``vehicle_variants.md``, ``vehicle_variants.json``, ``vehicle_variants.png``.
``--smoke`` runs the whole chain on tiny settings (a 70 s drive, one short training epoch,
lane changes cut to 2 s): a check that it works, not a result.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from controller.registry import CONTROLLER_NAMES, GEOMETRIC_NAMES

#: Friction -> the lane change of the paper's table at that friction.
FRICTION_SCENARIOS = {"high": "dlc_high_mu", "low": "dlc_low_mu"}
#: Controllers run with the nominal models: the paper's four and the geometric baselines.
NOMINAL_CONTROLLERS = CONTROLLER_NAMES + GEOMETRIC_NAMES
#: Controllers run again with the identified models (Koopman for the first two, the
#: fitted bicycle for LMPC).
IDENTIFIED_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: What an owner measures of a car and writes into the vehicle file for the bicycle fit:
#: the mass and the axle loads (weighing each axle gives lf and lr). The tyres and the yaw
#: inertia are not measured: the fit finds them.
MEASURED_FIELDS = ("mass", "lf", "lr")


@dataclass(frozen=True)
class StudySettings:
    """How much of each stage runs: ``drive_s`` the identification drive's length (s;
    None: the whole 612 s), ``run_s`` the lane changes' (None: whole), ``epochs`` the
    training's (None: the training's default) and ``training_options`` more
    ``koopman_train`` options."""

    drive_s: float | None = None
    run_s: float | None = None
    epochs: int | None = None
    training_options: tuple[str, ...] = ()


#: ``--smoke``: the chain end to end in about a minute (70 s of drive is above the 60 s
#: the training needs; the results mean nothing).
SMOKE = StudySettings(drive_s=70.0, run_s=2.0, epochs=1, training_options=("--steps-per-epoch", "3"))


#: The nominal sedan's entry: its lane changes with the nominal models, for reference.
REFERENCE = "nominal"


def settings_record(settings: StudySettings) -> dict[str, Any]:
    """``settings`` as they read back from a result's JSON (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(settings)))


def variant_scenario(name: str, variant: str | None, duration_s: float | None = None) -> Any:
    """Scenario ``name`` (shipped name or file) with the vehicle variant ``variant``
    (``[vehicle] variant``; None: the nominal car) and, given, another ``duration_s``:
    ``hil.scenario.Scenario``."""
    from hil.scenario import load_scenario

    scenario = dataclasses.replace(load_scenario(name), vehicle_variant=variant)
    return scenario if duration_s is None else dataclasses.replace(scenario, duration_s=duration_s)


def lane_change_runs(variant: str | None, controllers: Sequence[str], model_dir: Path | None,
                     settings: StudySettings) -> list[dict[str, Any]]:
    """Both lane changes on ``variant`` (None: the nominal car) with each of
    ``controllers``: the nominal models (``model_dir`` None) or the identified ones in
    ``model_dir`` (``koopman`` for the Koopman controllers, ``bicycle.json`` for LMPC).
    Returns one summary per run (``studies.paper_tables.run_summary`` plus variant,
    friction, model, seconds)."""
    from controller.registry import MODEL_FILE_KINDS, create_controller
    from studies.closed_loop import run_closed_loop
    from studies.paper_tables import run_summary

    runs = []
    for friction, scenario_name in FRICTION_SCENARIOS.items():
        scenario = variant_scenario(scenario_name, variant, settings.run_s)
        for controller in controllers:
            model = None if model_dir is None else \
                model_dir / ("koopman" if MODEL_FILE_KINDS[controller] == "koopman" else "bicycle.json")
            started = time.perf_counter()
            result = run_closed_loop(scenario, create_controller(controller, model_path=model))
            summary = run_summary(result)
            summary.update(variant=variant or REFERENCE, friction=friction, controller=controller,
                           model="nominal" if model is None else "identified",
                           seconds=round(time.perf_counter() - started, 2))
            runs.append(summary)
            print(f"{variant or REFERENCE} {friction} mu: {controller} ({summary['model']} model): e_Y RMSE "
                  f"{summary['tracking']['lateral_error_m']['rmse']:.4f} m"
                  + ("" if summary["completed"] else f", stopped: {summary['failure']}"), flush=True)
    return runs


def record_variant_drive(variant: str, work: Path, settings: StudySettings, reuse_log: bool) -> tuple[Path, dict[str, Any]]:
    """The identification drive on ``variant`` over CAN (LMPC, ``prbs-torque``), recorded
    to ``work``/drive.log; with ``reuse_log`` the recording already there. Returns the log
    and the drive's facts (``studies.identification.drive_over_can``, plus seconds)."""
    from studies.identification import IDENTIFICATION_SCENARIO_FILE, drive_over_can

    log, facts_file = work / "drive.log", work / "drive.json"
    if reuse_log and log.is_file() and facts_file.is_file():
        facts = json.loads(facts_file.read_text())
        if facts.get("drive_s") == settings.drive_s:
            return log, facts
    log.unlink(missing_ok=True)
    started = time.perf_counter()
    drive = drive_over_can(variant_scenario(str(IDENTIFICATION_SCENARIO_FILE), variant, settings.drive_s), log)
    drive.update(seconds=round(time.perf_counter() - started, 1), drive_s=settings.drive_s)
    facts_file.write_text(json.dumps(drive, indent=1) + "\n")
    return log, drive


def identify_variant(variant: str, log: Path, work: Path, settings: StudySettings) -> Path:
    """Train the Koopman model and fit the bicycle from ``log`` alone (``koopman_train
    --logs``), with a vehicle file of the variant's measured values (``MEASURED_FIELDS``).
    Returns the model folder (``koopman.npz``/``.json``, ``bicycle.json``, ``report.md``)."""
    from models.vehicle_variants import load_variant
    from studies.identification import identify, measured_vehicle_file

    params = load_variant(variant).params
    vehicle_file = measured_vehicle_file(work / "vehicle_measured.toml",
                                         {name: getattr(params, name) for name in MEASURED_FIELDS})
    model_dir = work / "model"
    identify(log, model_dir, settings.epochs, vehicle_file, settings.training_options)
    return model_dir


def study_variant(variant: str, work: Path, settings: StudySettings, reuse_log: bool) -> dict[str, Any]:
    """Stages 1-3 of the module docstring on one variant; the result is also written to
    ``work``/result.json."""
    from models.vehicle_variants import load_variant
    from studies.identification import bicycle_comparison

    work.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    runs = lane_change_runs(variant, NOMINAL_CONTROLLERS, None, settings)
    seconds["nominal_runs"] = time.perf_counter() - started
    log, drive = record_variant_drive(variant, work, settings, reuse_log)
    seconds["drive"] = drive["seconds"]  # the recording's, also when reused
    started = time.perf_counter()
    model_dir = identify_variant(variant, log, work, settings)
    seconds["training"] = time.perf_counter() - started
    started = time.perf_counter()
    runs += lane_change_runs(variant, IDENTIFIED_CONTROLLERS, model_dir, settings)
    seconds["identified_runs"] = time.perf_counter() - started
    car = load_variant(variant)
    result = {"variant": variant, "description": car.description, "overrides": dict(car.overrides),
              "drive": drive, "bicycle": bicycle_comparison(model_dir, car.params),
              "identified_model": json.loads((model_dir / "koopman.json").read_text()).get("settings"),
              "runs": runs, "seconds": {k: round(v, 1) for k, v in seconds.items()},
              "settings": settings_record(settings)}
    (work / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def reference_result(work: Path, settings: StudySettings) -> dict[str, Any]:
    """The nominal sedan with the nominal models on both lane changes (stage 1 only), for
    reference; also written to ``work``/result.json."""
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    runs = lane_change_runs(None, NOMINAL_CONTROLLERS, None, settings)
    result = {"variant": REFERENCE, "description": "the nominal D-class sedan (models/vehicle.toml), "
                                                   "the car the models were made for",
              "overrides": {}, "runs": runs, "seconds": {"nominal_runs": round(time.perf_counter() - started, 1)},
              "settings": settings_record(settings)}
    (work / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def run_study(variants: Sequence[str], out: Path, work: Path, settings: StudySettings,
              reuse_log: bool = False, reuse_results: bool = False) -> list[Path]:
    """The study on ``variants`` after the nominal sedan's reference runs; returns the
    report's files in ``out``."""
    from studies.machine import machine_description
    from studies.vehicle_variants_report import write_report

    results = []
    for variant in (REFERENCE, *variants):
        saved = work / variant / "result.json"
        if reuse_results and saved.is_file() and json.loads(saved.read_text())["settings"] == settings_record(settings):
            print(f"{variant}: results of {saved} reused", flush=True)
            results.append(json.loads(saved.read_text()))
        elif variant == REFERENCE:
            results.append(reference_result(work / variant, settings))
        else:
            results.append(study_variant(variant, work / variant, settings, reuse_log))
    return write_report(results, out, {"machine": machine_description(), "settings": settings_record(settings)})


def main(argv: Sequence[str] | None = None) -> int:
    """CLI (see the module docstring). Exit 0, or 2 for an unknown variant."""
    from models.vehicle_variants import VehicleVariantError, variant_names

    parser = argparse.ArgumentParser(prog="python -m studies.vehicle_variants", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=None, metavar="NAME",
                        help="variants of models/vehicle_variants.toml (default: all)")
    parser.add_argument("--out", type=Path, default=Path("results"),
                        help="folder of vehicle_variants.md / .json / .png (default results)")
    parser.add_argument("--work", type=Path, default=Path("build/vehicle_variants"),
                        help="folder of each variant's drive log, models and results")
    parser.add_argument("--epochs", type=int, default=None, help="training epochs (default: the training's)")
    parser.add_argument("--reuse-log", action="store_true",
                        help="train from the drive logs already in --work (skips the 612 s drives)")
    parser.add_argument("--reuse-results", action="store_true",
                        help="take a variant's results from --work when there (same settings): resume")
    parser.add_argument("--smoke", action="store_true",
                        help="tiny settings (70 s drive, one short epoch, 2 s lane changes): checks the chain")
    args = parser.parse_args(argv)
    try:
        known = variant_names()
    except VehicleVariantError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    variants = args.variants or list(known)
    unknown = [v for v in variants if v not in known]
    if unknown:
        print(f"error: --variants: unknown {', '.join(unknown)}; one of {', '.join(known)}", file=sys.stderr)
        return 2
    settings = SMOKE if args.smoke else StudySettings()
    if args.epochs is not None:
        settings = dataclasses.replace(settings, epochs=args.epochs)
    for file in run_study(variants, args.out, args.work, settings, args.reuse_log, args.reuse_results):
        print(f"wrote {file}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The vehicle-variant study's report (``studies.vehicle_variants``): Markdown, JSON, figure.

Works from the per-variant results of ``studies.vehicle_variants.study_variant`` (plain
dicts: ``variant``, ``description``, ``overrides``, ``runs``, ``seconds`` and, for the
variants, ``drive`` and ``bicycle``); the nominal sedan's entry (``variant`` "nominal")
has the nominal models' runs only.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from studies.machine_figures import MACHINE_KEYS, split_machine_keys
from studies.report import COLOUR, display_name

FRICTION_TITLES = {"high": "high friction: `dlc_high_mu`, 35 km/h, mu 0.85 (Table II's lane change)",
                   "low": "low friction: `dlc_low_mu`, 45-55 km/h, mu 0.5 (Table III's lane change)"}
#: Identified models, by controller.
IDENTIFIED_MODEL = {"eso-dkmpc": "identified Koopman", "dkmpc": "identified Koopman", "lmpc": "fitted bicycle"}
STEM = "vehicle_variants"
#: The stage times per car (wall clock, this machine), under the report's folder/logs/.
TIMES_FILE = "vehicle_variants_times.md"


def columns(results: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """The table's (controller, model) columns in run order: the nominal models first."""
    seen: dict[tuple[str, str], None] = {}
    for result in results:
        for run in result["runs"]:
            seen[(run["controller"], run["model"])] = None
    return sorted(seen, key=lambda key: key[1] != "nominal")


def column_title(controller: str, model: str) -> str:
    """``ESO-DKMPC`` (nominal model) or ``ESO-DKMPC, identified Koopman``."""
    name = display_name(controller)
    return name if model == "nominal" else f"{name}, {IDENTIFIED_MODEL.get(controller, model)}"


def cell(run: Mapping[str, Any] | None) -> str:
    """A run's e_Y RMSE (m), or where it stopped."""
    if run is None:
        return "-"
    rmse = run["tracking"]["lateral_error_m"]["rmse"]
    if run["completed"]:
        return f"{rmse:.4f}"
    how = "lost" if str(run.get("failure", "")).startswith("|e_Y|") else "failed"
    return f"{how} at {run['duration_s']:.1f} s ({rmse:.2f})"


def _find(runs: Sequence[Mapping[str, Any]], friction: str, controller: str, model: str) -> Mapping[str, Any] | None:
    return next((r for r in runs if (r["friction"], r["controller"], r["model"]) == (friction, controller, model)),
                None)


def results_table(results: Sequence[Mapping[str, Any]], friction: str) -> list[str]:
    """Markdown rows: one per variant, e_Y RMSE per (controller, model)."""
    keys = columns(results)
    lines = ["| car | " + " | ".join(column_title(*key) for key in keys) + " |",
             "|---|" + "---|" * len(keys)]
    for result in results:
        cells = [cell(_find(result["runs"], friction, *key)) for key in keys]
        lines.append(f"| {result['variant']} | " + " | ".join(cells) + " |")
    return lines


def variants_table(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown rows of each car's parameters and linear handling (the plant's own axle
    stiffnesses at its static loads, ``models.bicycle.nominal_model_params``)."""
    import dataclasses

    from models.bicycle import nominal_model_params
    from models.vehicle_params import load_vehicle_params

    lines = ["| car | what | mass (kg) | Iz (kg m^2) | wheelbase (m) | front load | CG height (m) "
             "| Cf / Cr (kN/rad) | K_us (mrad per m/s^2) | changed values |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for result in results:
        name = result["variant"]
        params = dataclasses.replace(load_vehicle_params(), **result["overrides"])
        bicycle = nominal_model_params(params)
        changed = ", ".join(f"{k} {v:g}" for k, v in result["overrides"].items()) or "-"
        lines.append(
            f"| {name} | {result['description']} | {params.mass:.0f} | {params.yaw_inertia:.0f} "
            f"| {params.wheelbase:.2f} | {params.lr / params.wheelbase:.0%} | {params.cg_height:.2f} "
            f"| {bicycle.cornering_stiffness_front / 1e3:.0f} / {bicycle.cornering_stiffness_rear / 1e3:.0f} "
            f"| {bicycle.understeer_gradient * 1e3:.2f} | {changed} |")
    return lines


def low_friction_goal(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """Issue 35's goal per variant: at low friction ESO-DKMPC's e_Y RMSE at most NMPC's,
    with the nominal or the identified model (a run that lost the car counts as not)."""
    lines = []
    for result in results:
        nmpc = _find(result["runs"], "low", "nmpc", "nominal")
        ours = {model: _find(result["runs"], "low", "eso-dkmpc", model) for model in ("nominal", "identified")}
        if nmpc is None or ours["identified"] is None:
            continue
        bound = nmpc["tracking"]["lateral_error_m"]["rmse"] if nmpc["completed"] else math.inf
        holds = [m for m, run in ours.items() if run is not None and run["completed"]
                 and run["tracking"]["lateral_error_m"]["rmse"] <= bound]
        verdict = f"holds ({' and '.join(holds)} model)" if holds else "does not hold"
        lines.append(f"- {result['variant']}: ESO-DKMPC {cell(ours['nominal'])} nominal, "
                     f"{cell(ours['identified'])} identified; NMPC {cell(nmpc)}: {verdict}.")
    return lines


def bicycle_table(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown rows: the fitted bicycle against each variant's own stiffnesses and inertia."""
    names = ("cornering_stiffness_front", "cornering_stiffness_rear", "yaw_inertia")
    lines = ["| car | " + " | ".join(f"{n}: own / fitted (fit error)" for n in names) + " |",
             "|---|" + "---|" * len(names)]
    for result in results:
        if "bicycle" not in result:
            continue
        rows = [result["bicycle"][n] for n in names]
        lines.append(f"| {result['variant']} | " + " | ".join(
            f"{r['changed_plant']:.0f} / {r['fitted']:.0f} ({r['fit_error_percent']:+.1f} %)" for r in rows) + " |")
    return lines


def times_table(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown rows of each car's stage times (s) and the drive's facts."""
    lines = ["| car | lane changes, nominal models (s) | drive over CAN (s) | drive max abs e_Y (m) "
             "| training (s) | lane changes, identified models (s) | total (s) |", "|---|---|---|---|---|---|---|"]
    for result in results:
        t = result["seconds"]
        drive = result.get("drive", {})
        max_e = drive.get("tracking", {}).get("lateral_error_m", {}).get("max_abs")

        def f(value: float | None) -> str:
            return "-" if value is None else f"{value:.0f}"

        lines.append(f"| {result['variant']} | {f(t.get('nominal_runs'))} | {f(t.get('drive'))} | "
                     f"{'-' if max_e is None else f'{max_e:.3f}'} | {f(t.get('training'))} | "
                     f"{f(t.get('identified_runs'))} | {sum(t.values()):.0f} |")
    return lines


def report_markdown(results: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> str:
    """The whole report (see the module docstring)."""
    settings = meta["settings"]
    smoke = any(settings.get(k) is not None for k in ("drive_s", "run_s"))
    lines = ["# Vehicle variants the learned model never saw", ""]
    if smoke:
        lines += [f"**Smoke settings** ({json.dumps(settings)}): a check that the study runs; "
                  "these figures are not results.", ""]
    lines += ["Each car of `models/vehicle_variants.toml` drives the paper's two lane changes with "
              "every controller on the models of the nominal sedan; then it is identified from its "
              "own CAN log as `make identify` identifies its changed plant (the 612 s identification "
              "drive over CAN with LMPC and the `prbs-torque` excitation at mu 0.85, "
              "`python -m models.koopman_train --logs` with a vehicle file of the car's weighed mass "
              "and axle positions) and ESO-DKMPC, DKMPC and LMPC drive again on the identified "
              "models. Closed loop without CAN (`studies.closed_loop`, the HIL's timing). "
              "`make vehicle-variants`; docs/vehicle-variants.md.", "",
              "## The cars", "", *variants_table(results), ""]
    for friction, title in FRICTION_TITLES.items():
        lines += [f"## e_Y RMSE (m), {title}", "",
                  "'lost at t s (RMSE)': the run stopped at |e_Y| > 10 m at t (its RMSE up to there); 'failed': the plant or the controller stopped it.", "",
                  *results_table(results, friction), ""]
    lines += ["## Goal of issue 35: at low friction ESO-DKMPC at most NMPC's e_Y RMSE", "",
              *low_friction_goal(results), "",
              "## The fitted bicycle against each car's own", "",
              "Own: the flat-track slope of the car's tyres at its static axle loads and its yaw "
              "inertia; fitted: `bicycle.json` of the training (mass, lf, lr given).", "",
              *bicycle_table(results), "",
              f"Stage times and the machine: `logs/{TIMES_FILE}` beside this file (not under version "
              "control), so a rerun of the same code rewrites the same bytes here.", ""]
    return "\n".join(lines)


def plot_report(results: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Bars of e_Y RMSE (log scale) per car and (controller, model), one panel per
    friction; a run that lost the car is a hatched bar at the top of the axis."""
    import matplotlib

    matplotlib.use("Agg")  # files only; never a display
    import matplotlib.pyplot as plt
    import numpy as np

    keys = columns(results)
    rmse = [run["tracking"]["lateral_error_m"]["rmse"] for r in results for run in r["runs"] if run["completed"]]
    bottom, top = 0.5 * min(rmse, default=1e-2), 3.0
    fig, axes = plt.subplots(len(FRICTION_TITLES), 1, figsize=(11, 8), sharex=True)
    width = 0.8 / len(keys)
    for ax, friction in zip(np.atleast_1d(axes), FRICTION_TITLES):
        for j, (controller, model) in enumerate(keys):
            x = np.arange(len(results)) + (j - (len(keys) - 1) / 2) * width
            runs = [_find(r["runs"], friction, controller, model) for r in results]
            heights = [np.nan if run is None else (run["tracking"]["lateral_error_m"]["rmse"]
                                                   if run["completed"] else top) for run in runs]
            hatch = [run is not None and not run["completed"] for run in runs]
            bars = ax.bar(x, heights, width, color=COLOUR.get(controller, "black"),
                          alpha=1.0 if model == "nominal" else 0.45,
                          edgecolor="black" if model != "nominal" else None, linewidth=0.6,
                          label=column_title(controller, model))
            for bar, lost in zip(bars, hatch):
                if lost:
                    bar.set_hatch("xx")
        ax.set_yscale("log")
        ax.set_ylim(bottom, top)
        ax.set_ylabel("e_Y RMSE (m)")
        ax.set_title(FRICTION_TITLES[friction].replace("`", ""), fontsize=10)
        ax.grid(axis="y", which="both", alpha=0.3)
    axes[-1].set_xticks(np.arange(len(results)), [r["variant"] for r in results])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, ncol=4, loc="lower center",
               title="pale bars: identified models; hatched to the top: lost the car", title_fontsize=8)
    fig.tight_layout(rect=(0.0, 0.1, 1.0, 1.0))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def inputs_only(result: Mapping[str, Any]) -> dict[str, Any]:
    """A car's result without what the machine decides: its stage times, the drive's wall
    time and each run's (``studies.machine_figures.MACHINE_KEYS``)."""
    kept = {k: v for k, v in result.items() if k != "seconds"}
    kept["runs"] = split_machine_keys(result["runs"])[0]
    if "drive" in result:
        kept["drive"] = {k: v for k, v in result["drive"].items() if k not in MACHINE_KEYS}
    return kept


def write_report(results: Sequence[Mapping[str, Any]], out: Path, meta: Mapping[str, Any]) -> list[Path]:
    """Write ``vehicle_variants.md``, ``.json`` and ``.png`` into ``out`` (the same bytes on
    any machine) and the stage times with ``meta["machine"]`` into ``out``/logs/; returns
    the first three."""
    out.mkdir(parents=True, exist_ok=True)
    markdown, document, figure = (out / f"{STEM}.md", out / f"{STEM}.json", out / f"{STEM}.png")
    shared = {k: v for k, v in meta.items() if k != "machine"}
    markdown.write_text(report_markdown(results, shared))
    document.write_text(json.dumps({**shared, "cars": [inputs_only(r) for r in results]}, indent=1) + "\n")
    (out / "logs").mkdir(exist_ok=True)
    (out / "logs" / TIMES_FILE).write_text(
        f"# Vehicle variants: stage times on {meta.get('machine', 'this machine')}\n\n"
        + "\n".join(times_table(results)) + "\n")
    return [markdown, document, plot_report(results, figure)]

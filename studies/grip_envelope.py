"""The MPCs' grip envelope: what the tuning procedure would choose, and what it does on the
lane changes (``make grip-envelope``).

The grip envelope (``controller.grip_envelope``, docs/grip-envelope.md) bounds the QP's
yaw-rate rows (NMPC's soft rows too) by (1 + margin) a_max / vx, a_max estimated from the rear axle's slip beyond
the nominal bicycle's linear need; ``grip_slip_excess`` (rad, 0 = off) is its threshold.
This study, with every other field at the tuning file's value and the envelope's other three
fields starting from their defaults (:func:`starting_tuning`, not from the tuning file, which
holds this stage's own earlier choice: so a second run chooses what the first did):

1. **The tuning stage**: each MPC (:data:`ENVELOPE_CONTROLLERS`: the QP MPCs and NMPC) at
   each ``grip_slip_excess`` of :data:`SLIP_EXCESSES_DEG` (off, 2 to 6 degrees) on the tuning set with disturbances
   (``studies.observer_tuning.disturbed_tuning_set``, 22 runs) and on a limit set: its 11
   undisturbed manoeuvres on a plant whose rear tyres have :data:`LIMIT_REAR_SCALE` of their
   cornering stiffness (an oversteering car at its limit; named ``<manoeuvre>@rear_x0.65``),
   and on the same with +150 kg and the steering's time constant x2 (``...+150kg+lag_x2``).
   The objective is the procedure's (``studies.tuning_sweep_executor.objective``: the mean
   e_Y RMSE, a run that does not complete counts 10 m) over the 44 runs; the chosen value
   the lowest objective, ties to off.
2. **The refinement**: for each MPC whose choice is on, the envelope's other fields one at a
   time (:data:`REFINE_AXES`: the margin, then the recovery, then the peak memory), each over
   its whole grid on the same 44 runs at the controller's choices so far; the field's default
   (:data:`GRIP_DEFAULTS`) is the incumbent, so a tie keeps it. A choice at a grid's end is
   marked in the report (a value beyond it was not run), except a margin of 0, the field's
   own bound.
3. **The evaluation**, on scenarios the tuning never saw: Tables II / III's lane changes on
   the nominal plant and on make identify's changed plant
   (``studies.identification.changed_params``: mass +300 kg, rear tyres x0.8, steering lag
   x3; named ``<scenario>@changed``), each MPC at each value (its chosen value among
   them, and its refined setting where the refinement moved a field), Stanley (no envelope)
   beside them.
4. ``grip_envelope.png``: e_Y over time on the changed plant's low-mu lane change.

The plants are built as a closed-loop campaign cell builds them
(``studies.campaign.closed_loop_cell.plant_for``): the rear tyres and the changed plant are
vehicle faults of the scenario's ``[faults]`` table (``hil.faults.VehicleFaults``).

The procedure's last stage (after ``make tune`` and the observer stages, whose choices it
takes as given): it writes each MPC's four grip fields into ``controller/tuning.toml``
(``--no-write``: only the report).

Usage: ``python -m studies.grip_envelope [--out DIR] [--workers N] [--no-progress] [--no-write]``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import time
import types
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from controller.tuning import DEFAULT_TUNING_PATH, MpcTuning, load_tuning
from hil.scenario import Scenario, load_scenario
from studies.closed_loop import ClosedLoopResult
from studies.observer_speed import run_on_changed_plant
from studies.observer_tuning import disturbed_tuning_set
from studies.pose_step import QP_CONTROLLERS
from studies.tuning_file import update_tuning_text
from studies.tuning_sweep_executor import Evaluation, Job, SweepExecutor, best, build_controller, objective
from studies.tuning_sweep_grids import Setting, with_setting

#: The swept field and its values (degrees; 0 = off, the shipped value).
FIELD = "grip_slip_excess"
SLIP_EXCESSES_DEG = (0.0, 2.0, 3.0, 4.0, 5.0, 6.0)
#: The refinement's fields, in their order, and the values each is tried at (its default
#: among them, tried first): the bound's margin over the estimate (from 0, no margin), the
#: estimate's return once the rear axle grips again (m/s^2 per s), the peak's memory (s).
REFINE_AXES: tuple[tuple[str, tuple[float, ...]], ...] = (
    ("grip_margin", (0.0, 0.05, 0.1, 0.2)),
    ("grip_recovery", (5.0, 10.0, 20.0, 40.0, 80.0, 160.0)),
    ("grip_peak_time", (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)),
)
#: The refined fields' defaults (the tuning tables' own, ``controller.tuning.MpcTuning``):
#: where the stage starts each field, whatever the tuning file holds.
GRIP_DEFAULTS: dict[str, float] = {f.name: float(f.default) for f in dataclasses.fields(MpcTuning)
                                   if f.name in dict(REFINE_AXES)}
#: Refined fields whose smallest value is the field's own bound (no mark at that end).
BOUNDED_BELOW = {"grip_margin": 0.0}
#: Every field the stage writes, per MPC table.
WRITTEN_FIELDS = (FIELD,) + tuple(name for name, _ in REFINE_AXES)
#: The comment line the written tables carry (studies.tuning_file).
TUNING_COMMENT = "chosen by make grip-envelope on the tuning set with disturbances and the limit set, " \
    "results/grip_envelope.md"
#: The controllers with the envelope (every MPC) and those without it, run beside them.
ENVELOPE_CONTROLLERS = QP_CONTROLLERS + ("nmpc",)
REFERENCE_CONTROLLERS = ("stanley",)
#: The limit set's plants: the rear tyres' cornering stiffness times LIMIT_REAR_SCALE (an
#: oversteering car at its limit), alone and with a heavier car whose steering is slower
#: (LIMIT_SLOW_MASS_KG, the steering's time constant x LIMIT_SLOW_LAG_FACTOR: make
#: observer-speed's changed plants' values). Disjoint from the changed plant's rear tyres x0.8
#: with +300 kg and lag x3.
LIMIT_REAR_SCALE = 0.65
LIMIT_SLOW_MASS_KG = 150.0
LIMIT_SLOW_LAG_FACTOR = 2.0
#: How many of ``disturbed_tuning_set``'s runs are undisturbed (its first ones).
UNDISTURBED_RUNS = 11
#: The evaluation: Tables II / III's lane changes, on the nominal and the changed plant.
TABLE_SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
CHANGED_SUFFIX = "@changed"
#: The figure: the changed plant's low-mu lane change, these controllers off, at
#: FIGURE_SLIP_EXCESS_DEG and at their chosen value.
FIGURE_SCENARIO = f"dlc_low_mu{CHANGED_SUFFIX}"
FIGURE_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc", "nmpc")
FIGURE_SLIP_EXCESS_DEG = 3.0

_FAILURE_TIME = re.compile(r"at t = ([0-9.]+) s")


def setting(degrees: float) -> Setting:
    """The one-field override of ``grip_slip_excess`` (given in degrees, set in radians)."""
    return ((FIELD, math.radians(degrees)),)


def degrees_of(evaluation: Evaluation) -> float | None:
    """The evaluation's ``grip_slip_excess`` in degrees (None: a reference controller)."""
    value = dict(evaluation.setting).get(FIELD)
    return None if value is None else round(math.degrees(value), 6)


def label(degrees: float | None) -> str:
    """A value's name in tables and legends."""
    if degrees is None:
        return "(no envelope)"
    return "off" if degrees == 0.0 else f"{degrees:g} deg"


def setting_label(setting: Setting) -> str:
    """A setting's name: its ``grip_slip_excess`` and any refined field (``margin 0.2``)."""
    values = dict(setting)
    text = label(None if FIELD not in values else round(math.degrees(values[FIELD]), 6))
    refined = [f"{name.removeprefix('grip_').replace('_', ' ')} {value:g}" for name, value in setting if name != FIELD]
    return ", ".join([text] + refined)


def with_vehicle_faults(scenario: Scenario, suffix: str, **faults: float) -> Scenario:
    """``scenario`` renamed ``<name><suffix>`` with ``faults`` (``hil.faults.VehicleFaults``
    fields) added to its ``[faults] vehicle`` table, so that ``plant_for`` builds the plant."""
    table = dict(scenario.faults)
    table["vehicle"] = {**dict(table.get("vehicle", {})), **faults}
    return dataclasses.replace(scenario, name=f"{scenario.name}{suffix}", faults=types.MappingProxyType(table))


def on_soft_rear_tyres(scenario: Scenario) -> Scenario:
    """``scenario`` on a plant with the rear tyres at :data:`LIMIT_REAR_SCALE` of their
    cornering stiffness, named ``<name>@rear_x0.65``."""
    return with_vehicle_faults(scenario, f"@rear_x{LIMIT_REAR_SCALE:g}", cornering_stiffness_rear_scale=LIMIT_REAR_SCALE)


def on_slow_car_at_its_limit(scenario: Scenario) -> Scenario:
    """``scenario`` on the rear tyres of :func:`on_soft_rear_tyres` with
    :data:`LIMIT_SLOW_MASS_KG` more mass and the steering's time constant
    x :data:`LIMIT_SLOW_LAG_FACTOR`, named ``<name>@rear_x0.65+150kg+lag_x2``."""
    from models.vehicle_params import load_vehicle_params

    nominal_lag = load_vehicle_params().steer_time_constant
    return with_vehicle_faults(
        scenario, f"@rear_x{LIMIT_REAR_SCALE:g}+{LIMIT_SLOW_MASS_KG:g}kg+lag_x{LIMIT_SLOW_LAG_FACTOR:g}",
        cornering_stiffness_rear_scale=LIMIT_REAR_SCALE, mass_offset_kg=LIMIT_SLOW_MASS_KG,
        steer_extra_lag_s=(LIMIT_SLOW_LAG_FACTOR - 1.0) * nominal_lag)


def on_changed_plant(scenario: Scenario) -> Scenario:
    """``scenario`` on make identify's changed plant (``studies.identification.changed_params``
    as vehicle faults, as its identification drive injects them), named ``<name>@changed``."""
    from models.vehicle_params import load_vehicle_params
    from studies.identification import CHANGED_LAG_FACTOR, CHANGED_MASS_OFFSET_KG, CHANGED_REAR_STIFFNESS_SCALE

    nominal_lag = load_vehicle_params().steer_time_constant
    return with_vehicle_faults(scenario, CHANGED_SUFFIX, mass_offset_kg=CHANGED_MASS_OFFSET_KG,
                               steer_extra_lag_s=(CHANGED_LAG_FACTOR - 1.0) * nominal_lag,
                               cornering_stiffness_rear_scale=CHANGED_REAR_STIFFNESS_SCALE)


def tuning_scenarios() -> tuple[list[Scenario], list[Scenario]]:
    """The tuning stage's runs: the tuning set with disturbances (22) and the limit set (22:
    its undisturbed manoeuvres on each limit plant)."""
    disturbed = disturbed_tuning_set()
    undisturbed = disturbed[:UNDISTURBED_RUNS]
    return disturbed, [on_soft_rear_tyres(s) for s in undisturbed] + [on_slow_car_at_its_limit(s) for s in undisturbed]


def evaluation_scenarios() -> list[Scenario]:
    """The lane changes on the nominal plant, then on the changed plant."""
    nominal = [load_scenario(name) for name in TABLE_SCENARIOS]
    return nominal + [on_changed_plant(s) for s in nominal]


def starting_tuning(tuning: Any) -> Any:
    """``tuning`` with every envelope controller's refined grip fields at
    :data:`GRIP_DEFAULTS`: the stage's runs do not depend on its own earlier choice."""
    start = tuple(GRIP_DEFAULTS.items())
    for name in ENVELOPE_CONTROLLERS:
        tuning = with_setting(tuning, name, start)
    return tuning


def tuning_jobs() -> list[Job]:
    """Each MPC at each value, off first."""
    return [(name, "grip", setting(d)) for name in ENVELOPE_CONTROLLERS for d in SLIP_EXCESSES_DEG]


def evaluation_jobs(chosen: Mapping[str, Evaluation] | None = None) -> list[Job]:
    """The tuning jobs, each refined choice of ``chosen`` that is not among them, and the
    reference controllers as the tuning file has them."""
    jobs = tuning_jobs()
    settings = {(name, s) for name, _, s in jobs}
    refined = [(name, "grip", e.setting) for name, e in (chosen or {}).items() if (name, e.setting) not in settings]
    return jobs + refined + [(name, "reference", ()) for name in REFERENCE_CONTROLLERS]


def evaluate(jobs: Sequence[Job], scenarios: Sequence[Scenario], tuning: Any, workers: int, progress: bool,
             desc: str) -> list[Evaluation]:
    """``jobs`` on ``scenarios`` on the plants their ``[faults]`` tables build, in job order."""
    bar = tqdm(total=len(jobs) * len(scenarios), desc=desc, unit="run", disable=not progress)
    executor = SweepExecutor(scenarios, tuning, run_on_changed_plant, workers, bar)
    try:
        return executor.evaluate(jobs)
    finally:
        executor.close()
        bar.close()


# ---------------------------------------------------------------------------- the choice

def subset_objective(evaluation: Evaluation, names: Sequence[str]) -> float:
    """The procedure's objective (m) of ``evaluation`` over the runs ``names`` only."""
    return objective({n: evaluation.rmse_m[n] for n in names}, {n: evaluation.completed[n] for n in names})


def choices(evaluations: Sequence[Evaluation]) -> dict[str, Evaluation]:
    """Controller -> its evaluation with the lowest objective; on a tie the first in
    ``evaluations`` (off comes first: ties go to off)."""
    by_controller: dict[str, list[Evaluation]] = {}
    for e in evaluations:
        by_controller.setdefault(e.controller, []).append(e)
    return {name: best(group) for name, group in by_controller.items()}


def is_on(evaluation: Evaluation) -> bool:
    """Whether the evaluation's setting has the envelope on."""
    return dict(evaluation.setting).get(FIELD, 0.0) > 0.0


#: One round of the refinement: its field and, per controller, the evaluations in the
#: order they were compared (the incumbent first).
Round = tuple[str, dict[str, list[Evaluation]]]


def refine(stage_one: Mapping[str, Evaluation],
           run: Callable[[Sequence[Job]], list[Evaluation]]) -> tuple[list[Round], dict[str, Evaluation]]:
    """The refinement over :data:`REFINE_AXES`, field by field, of every controller whose
    ``stage_one`` choice is on (its runs at :func:`starting_tuning`): each field's default
    (:data:`GRIP_DEFAULTS`) is the incumbent, whose runs are those of the choice so far (not
    run again). ``run`` evaluates jobs in order. Returns the rounds and each controller's
    final choice (``stage_one``'s where off)."""
    chosen = dict(stage_one)
    rounds: list[Round] = []
    for field, values in REFINE_AXES:
        on = [name for name, e in chosen.items() if is_on(e)]
        jobs = [(name, "grip-refine", chosen[name].setting + ((field, value),))
                for name in on for value in values if value != GRIP_DEFAULTS[field]]
        tried = run(jobs) if jobs else []
        compared = {name: [chosen[name]] + [e for e in tried if e.controller == name] for name in on}
        for name, group in compared.items():
            chosen[name] = best(group)
        rounds.append((field, compared))
    return rounds, chosen


def written_settings(chosen: Mapping[str, Evaluation]) -> dict[str, Setting]:
    """Each controller's four grip fields as the tuning file gets them: the choice's, the
    default (:data:`GRIP_DEFAULTS`, where the stage started) where the choice did not name a
    field."""
    values = {name: {**GRIP_DEFAULTS, **dict(e.setting)} for name, e in chosen.items()}
    return {name: tuple((f, values[name][f]) for f in WRITTEN_FIELDS) for name in chosen}


def grid_edge(field: str, value: float) -> str:
    """The report's mark for a refined ``field`` chosen at ``value``: at its grid's largest
    or smallest value (a value beyond it was not run), or '' (inside, or at the field's own
    bound, :data:`BOUNDED_BELOW`)."""
    values = dict(REFINE_AXES)[field]
    if value == max(values):
        return " (the grid's largest value: a larger one was not run)"
    if value == min(values) and BOUNDED_BELOW.get(field) != value:
        return " (the grid's smallest value: a smaller one was not run)"
    return ""


# ---------------------------------------------------------------------------- the report

def outcome(evaluation: Evaluation, scenario: str) -> str:
    """A run's e_Y RMSE (m), or 'lost at t s' (|e_Y| beyond 10 m) / 'failed at t s'."""
    if evaluation.completed[scenario]:
        return f"{evaluation.rmse_m[scenario]:.3f}"
    failure = evaluation.failure[scenario] or ""
    how = "lost" if failure.startswith("|e_Y|") else "failed"
    found = _FAILURE_TIME.search(failure)
    return f"{how} at {float(found.group(1)):.1f} s" if found else how


def _stored(evaluation: Evaluation) -> dict[str, Any]:
    """An evaluation for the JSON without its wall time (a rerun writes the same bytes)."""
    fields = evaluation.as_dict()
    fields.pop("seconds")
    return fields


def _mm(value_m: float) -> str:
    return f"{1e3 * value_m:.2f}"


def report(tuning_set: Sequence[Evaluation], studies: Sequence[Evaluation], disturbed: Sequence[str],
           limit: Sequence[str], *, command: str, minutes: float, rounds: Sequence[Round] = (),
           final: Mapping[str, Evaluation] | None = None, written: bool = False) -> tuple[str, dict[str, Any]]:
    """Markdown and JSON of the study: ``tuning_set`` the tuning stage's evaluations (over
    the runs ``disturbed`` and ``limit``), ``rounds`` the refinement's, ``final`` each
    controller's final choice (default: the tuning stage's), ``studies`` the evaluation's;
    ``written``: the choices went into the tuning file."""
    chosen = choices(tuning_set)
    final = dict(final) if final is not None else chosen
    where = ("The choices are written into `controller/tuning.toml` (each MPC's four grip fields)." if written
             else "Run with `--no-write`: the tuning file was left as it was.")
    lines = ["# The grip envelope: the tuning procedure's choice, and the lane changes", "",
             f"Written by `{command}` in {minutes:.1f} min (`studies/grip_envelope.py`; its docstring says what "
             f"and why, docs/grip-envelope.md what the envelope is). Closed loop without CAN; every field but "
             f"the grip envelope's at the tuning file's value, the envelope's margin, recovery and peak memory "
             f"starting from their defaults ({', '.join(f'{k} {v:g}' for k, v in GRIP_DEFAULTS.items())}), not "
             f"from the file's (this stage's own earlier choice). The procedure's last stage: {where}", "",
             "Question: does the tuning procedure switch the envelope on, at which setting, and what "
             "does that do on Tables II / III's lane changes on the nominal plant and on make identify's changed "
             "plant (mass +300 kg, rear tyres x0.8, steering lag x3), where the nominal-model MPCs spin on the "
             "low-mu lane change?", "",
             f"## The tuning stage ({len(disturbed) + len(limit)} runs per setting)", "",
             f"The procedure's objective (mean e_Y RMSE, mm; a run that does not complete counts 10 m) over the "
             f"tuning set with disturbances ({len(disturbed)} runs) and the limit set ({len(limit)} runs: its "
             f"undisturbed manoeuvres with the rear tyres' cornering stiffness x{LIMIT_REAR_SCALE:g}, and with "
             f"that, {LIMIT_SLOW_MASS_KG:+g} kg and the steering's time constant x{LIMIT_SLOW_LAG_FACTOR:g}), "
             "and over each part; not completed: runs that did not complete. The chosen value has the lowest objective "
             "over all runs (ties to off).", "",
             "| controller | grip_slip_excess | objective (all) | tuning set | limit set | not completed | chosen |",
             "|---|---|---:|---:|---:|---:|---|"]
    summary: dict[str, Any] = {"field": FIELD, "values_deg": list(SLIP_EXCESSES_DEG),
                               "limit_rear_scale": LIMIT_REAR_SCALE,
                               "limit_slow_car": {"mass_offset_kg": LIMIT_SLOW_MASS_KG,
                                                  "lag_factor": LIMIT_SLOW_LAG_FACTOR}, "tuning_runs": {"disturbed": list(disturbed),
                                                                                      "limit": list(limit)},
                               "tuning": {}, "chosen_deg": {}, "evaluation": {}}
    for e in tuning_set:
        degrees = degrees_of(e)
        failed = sum(not ok for ok in e.completed.values())
        mark = "**chosen**" if chosen[e.controller] is e else ""
        lines.append(f"| {e.controller} | {label(degrees)} | {_mm(e.objective_m)} | "
                     f"{_mm(subset_objective(e, disturbed))} | {_mm(subset_objective(e, limit))} | {failed} | {mark} |")
        summary["tuning"][f"{e.controller}@{degrees:g}"] = {
            **_stored(e), "objective_disturbed_m": subset_objective(e, disturbed),
            "objective_limit_m": subset_objective(e, limit)}
    off = {e.controller: e for e in tuning_set if degrees_of(e) == 0.0}
    lines += ["", "Chosen per controller (objective over all runs, mm, off -> chosen):", ""]
    for name, e in chosen.items():
        summary["chosen_deg"][name] = degrees_of(e)
        edge = (" (the grid's largest value: a larger one was not run)"
                if degrees_of(e) == max(SLIP_EXCESSES_DEG) else "")
        lines.append(f"- {name}: {label(degrees_of(e))}, {_mm(off[name].objective_m)} -> {_mm(e.objective_m)}{edge}")
    lines += refinement_lines(rounds, final, summary)
    lines += evaluation_lines(studies, final, summary)
    lines += ["", f"![e_Y on {FIGURE_SCENARIO}: ESO-DKMPC, DKMPC, LMPC, NMPC off, at {FIGURE_SLIP_EXCESS_DEG:g} deg "
              "and at the chosen value](grip_envelope.png)", "", "## Commands", "",
              "    make grip-envelope", "    .venv/bin/python -m studies.grip_envelope --out /tmp/grip --workers 2",
              "    .venv/bin/python -m pytest -q tests/test_grip_envelope_study.py"]
    return "\n".join(lines) + "\n", summary


def refinement_lines(rounds: Sequence[Round], final: Mapping[str, Evaluation],
                     summary: dict[str, Any]) -> list[str]:
    """The refinement's section of the report (``summary["refinement"]`` and
    ``summary["chosen"]`` filled)."""
    summary["refinement"] = {field: {name: [{"setting": [list(item) for item in e.setting],
                                             "objective_m": e.objective_m} for e in group]
                                     for name, group in compared.items()} for field, compared in rounds}
    summary["chosen"] = {name: setting_label(e.setting) for name, e in final.items()}
    edges = {name: {field: value for field, value in e.setting if field in GRIP_DEFAULTS and grid_edge(field, value)}
             for name, e in final.items()}
    summary["grid_edges"] = {name: fields for name, fields in edges.items() if fields}
    if not rounds:
        return []
    lines = ["", f"## The refinement ({', '.join(field for field, _ in rounds)}, one at a time)", "",
             "Each MPC whose choice is on, each field at its values on the same runs, at the choices so far; the "
             "first row of each field is the incumbent (the field's default, where the stage starts it, so a tie "
             "keeps it). Objective "
             "over all runs (mm).", "",
             "| controller | field | setting | objective (all) | not completed | chosen |",
             "|---|---|---|---:|---:|---|"]
    for field, compared in rounds:
        for name, group in compared.items():
            winner = best(group)
            for e in group:
                failed = sum(not ok for ok in e.completed.values())
                lines.append(f"| {name} | {field} | {setting_label(e.setting)} | {_mm(e.objective_m)} | {failed} | "
                             f"{'**chosen**' if e is winner else ''} |")
    lines += ["", "Final choice per controller: " + "; ".join(f"{name} {setting_label(e.setting)} "
                                                              f"({_mm(e.objective_m)} mm)"
                                                              for name, e in final.items()) + "."]
    for name, fields in summary["grid_edges"].items():
        lines += [f"- {name}: {field.removeprefix('grip_').replace('_', ' ')} {value:g}{grid_edge(field, value)}"
                  for field, value in fields.items()]
    return lines


def evaluation_lines(studies: Sequence[Evaluation], chosen: Mapping[str, Evaluation],
                     summary: dict[str, Any]) -> list[str]:
    """The evaluation's section of the report (``summary["evaluation"]`` filled)."""
    names = list(studies[0].rmse_m) if studies else []
    lines = ["", "## The evaluation: Tables II / III's lane changes", "",
             "e_Y RMSE (m), or where the run stopped ('lost at t s': |e_Y| beyond 10 m); `@changed`: make "
             "identify's changed plant. Chosen: the tuning stage's value. Stanley has no envelope.", "",
             "| controller | grip_slip_excess | " + " | ".join(names) + f" | max abs e_Y (m), {FIGURE_SCENARIO} |",
             "|---|---|" + "---:|" * (len(names) + 1)]
    for e in studies:
        degrees = degrees_of(e)
        value = setting_label(e.setting) + (" (chosen)" if is_chosen(e, chosen) else "")
        worst = e.max_abs_m.get(FIGURE_SCENARIO, math.nan)
        lines.append(f"| {e.controller} | {value} | " + " | ".join(outcome(e, s) for s in names)
                     + f" | {worst:.3f} |")
        refined = "".join(f",{name.removeprefix('grip_')}={value:g}" for name, value in e.setting if name != FIELD)
        summary["evaluation"][f"{e.controller}@{'-' if degrees is None else f'{degrees:g}'}{refined}"] = _stored(e)
    ranked = ranking(studies, chosen)
    if ranked:
        lines += ["", f"On `{FIGURE_SCENARIO}`, each MPC at its chosen value and Stanley, by e_Y RMSE "
                  "(completed runs first): " + ", ".join(ranked) + "."]
    return lines


def is_chosen(evaluation: Evaluation, chosen: Mapping[str, Evaluation]) -> bool:
    """Whether ``evaluation`` ran its controller's chosen setting."""
    choice = chosen.get(evaluation.controller)
    return choice is not None and dict(choice.setting) == dict(evaluation.setting)


def ranking(studies: Sequence[Evaluation], chosen: Mapping[str, Evaluation]) -> list[str]:
    """The controllers on :data:`FIGURE_SCENARIO` (the MPCs at their chosen value) with their
    outcome: the completed ones by e_Y RMSE, then the others, the longest-lasting first."""
    rows = [e for e in studies if FIGURE_SCENARIO in e.rmse_m and (
        e.controller not in chosen or is_chosen(e, chosen))]

    def key(e: Evaluation) -> tuple[bool, float]:
        if e.completed[FIGURE_SCENARIO]:
            return False, e.rmse_m[FIGURE_SCENARIO]
        found = _FAILURE_TIME.search(e.failure[FIGURE_SCENARIO] or "")
        return True, -float(found.group(1)) if found else 0.0

    return [f"{e.controller} {outcome(e, FIGURE_SCENARIO)}" for e in sorted(rows, key=key)]


# ---------------------------------------------------------------------------- the figure

def figure_settings(name: str, chosen: Mapping[str, Setting]) -> list[Setting]:
    """The settings the figure shows for controller ``name``: off, FIGURE_SLIP_EXCESS_DEG and
    its chosen setting (when another)."""
    shown: list[Setting] = []
    for candidate in (setting(0.0), setting(FIGURE_SLIP_EXCESS_DEG), chosen.get(name, setting(0.0))):
        if all(dict(candidate) != dict(other) for other in shown):
            shown.append(candidate)
    return shown


def figure_runs(tuning: Any, chosen: Mapping[str, Setting], progress: bool) -> dict[str, ClosedLoopResult]:
    """The figure's runs with traces: key ``name@setting label``."""
    scenario = next(s for s in evaluation_scenarios() if s.name == FIGURE_SCENARIO)
    keys = [(name, shown) for name in FIGURE_CONTROLLERS for shown in figure_settings(name, chosen)]
    runs = {}
    for name, shown in tqdm(keys, desc="figure traces", unit="run", disable=not progress):
        controller = build_controller(name, with_setting(tuning, name, shown))
        runs[f"{name}@{setting_label(shown)}"] = run_on_changed_plant(scenario, controller)
    return runs


#: The figure's e_Y range (m): the lost runs leave it upwards, the others stay within.
FIGURE_RANGE_M = 1.5


def figure(runs: Mapping[str, ClosedLoopResult], chosen: Mapping[str, Setting], out: Path) -> None:
    """e_Y (m) over time on :data:`FIGURE_SCENARIO`: each figure controller off, at
    FIGURE_SLIP_EXCESS_DEG and at its chosen setting, one panel each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(len(FIGURE_CONTROLLERS), 1, figsize=(9, 2.5 * len(FIGURE_CONTROLLERS)), sharex=True)
    for ax, name in zip(np.atleast_1d(axes), FIGURE_CONTROLLERS):
        for shown, style in zip(figure_settings(name, chosen), ("-", "-.", ":")):
            result = runs[f"{name}@{setting_label(shown)}"]
            mark = " (chosen)" if dict(shown) == dict(chosen.get(name, setting(0.0))) else ""
            end = "" if result.completed else " (lost)"
            ax.plot(result.trace.time_s, result.trace.lateral_error, style,
                    label=f"{name}, {setting_label(shown)}{mark}{end}")
        ax.set_ylim(-FIGURE_RANGE_M, FIGURE_RANGE_M)
        ax.set_ylabel("e_Y (m)")
        ax.legend(loc="lower left", fontsize=8)
        ax.grid(True, lw=0.3)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.suptitle(f"{FIGURE_SCENARIO}: e_Y with the grip envelope off, at {FIGURE_SLIP_EXCESS_DEG:g} deg\n"
                 "and at the chosen value (lost runs leave the axis)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.grip_envelope", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="parallel runs (Ray)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--tuning", type=Path, default=DEFAULT_TUNING_PATH,
                        help="the tuning file read, and written with the choices (default controller/tuning.toml)")
    parser.add_argument("--no-write", action="store_true", help="write the report only, not the tuning file")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    started = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    tuning = starting_tuning(load_tuning(args.tuning))
    text_before = args.tuning.read_text(encoding="utf-8")
    progress = not args.no_progress
    disturbed, limit = tuning_scenarios()
    tuning_set = evaluate(tuning_jobs(), disturbed + limit, tuning, args.workers, progress, "tuning stage")
    rounds, final = refine(choices(tuning_set),
                           lambda jobs: evaluate(jobs, disturbed + limit, tuning, args.workers, progress, "refinement"))
    studies = evaluate(evaluation_jobs(final), evaluation_scenarios(), tuning, args.workers, progress, "evaluation")
    chosen = {name: e.setting for name, e in final.items()}
    runs = figure_runs(tuning, chosen, progress)
    command = "python -m studies.grip_envelope " + " ".join(sys.argv[1:] if argv is None else argv)
    text, summary = report(tuning_set, studies, [s.name for s in disturbed], [s.name for s in limit],
                           command=command.strip(), minutes=(time.monotonic() - started) / 60.0, rounds=rounds,
                           final=final, written=not args.no_write)
    (args.out / "grip_envelope.md").write_text(text)
    (args.out / "grip_envelope.json").write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
    figure(runs, chosen, args.out / "grip_envelope.png")
    print(text)
    if not args.no_write:
        if args.tuning.read_text(encoding="utf-8") != text_before:
            print(f"error: {args.tuning} changed while the stage ran; not written", file=sys.stderr)
            return 1
        temporary = args.tuning.with_name(args.tuning.name + ".tmp")
        temporary.write_text(update_tuning_text(text_before, written_settings(final),
                                                comment=TUNING_COMMENT), encoding="utf-8")
        os.replace(temporary, args.tuning)
        print(f"wrote the grip fields into {args.tuning}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

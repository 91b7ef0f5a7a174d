"""The tuning sweep's reports: ``tuning_sweep.md`` (the procedure, then per controller the
choice and the best settings), ``tuning_sweep.png`` (every setting's objective) and
``tuning_sweep.json`` (every evaluation), and the sweep read back from that document
(``--report-from``, ``--reuse``, ``--merge`` of ``studies.tuning_sweep``).
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import StudyError
from studies.tuning_sweep_executor import FAILURE_PENALTY_M, Evaluation, best
from studies.tuning_sweep_grids import (EXTRA_OBSERVER_STARTS, LOW_SPEED_GRID, OBSERVER_FIELDS,
                                        OBSERVER_GRID, OBSERVER_START, WEIGHT_GRID, Setting, SweepGrid,
                                        setting_text)
from studies.tuning_sweep_procedure import MAX_EXTRA_ROUNDS, TOP_N, ControllerSweep

def _grid_text(grid: SweepGrid) -> str:
    return "; ".join(f"{name} {{{', '.join(f'{v:g}' for v in values)}}}" for name, values in grid.levels)


def sweep_markdown(sweeps: Sequence[ControllerSweep], names: Sequence[str],
                   context: Mapping[str, str],
                   weight_grid: SweepGrid = WEIGHT_GRID, observer_grid: SweepGrid = OBSERVER_GRID,
                   observer_start: Setting = OBSERVER_START) -> str:
    """The report: the procedure, then per controller its grid, choice and top settings
    (``names``: the tuning scenarios' names)."""
    out = ["### Tuning sweep on the tuning set (`make tune`)", "",
           f"Every controller tuned by the same procedure (`studies/tuning_sweep.py`) on the "
           f"{len(names)} tuning scenarios of `hil/scenarios/tuning/` ({', '.join(names)}); "
           "the double lane changes of Tables II / III are not among them. Objective: the mean "
           f"e_Y RMSE over the tuning scenarios, {FAILURE_PENALTY_M:g} m for a run that does not complete.",
           "",
           f"- Stage 1, MPC weights (every MPC, {len(weight_grid)} settings): {_grid_text(weight_grid)}.",
           f"- Stage 2, observer (controllers with observer fields, {len(observer_grid)} settings at "
           f"the best weights): {_grid_text(observer_grid)}; during stage 1 the observer is at "
           f"{setting_text(observer_start)}"
           + "".join(f" and again at {setting_text(s)}" for s in EXTRA_OBSERVER_STARTS) + ".",
           f"- Then, for controllers with observer fields, alternately the weight grid at the best "
           f"observer setting and the observer grid at the best weights, until a round keeps the best "
           f"(at most {MAX_EXTRA_ROUNDS} rounds; evaluations of these rounds are listed under the "
           f"stage of their grid).",
           f"- Stage 4, low-speed weights (every MPC, {len(LOW_SPEED_GRID)} settings at the best "
           f"setting so far): {_grid_text(LOW_SPEED_GRID)}; the weights the MPC uses at and below the "
           "speed schedule's low knot, blended linearly in vx into the others up to its high knot "
           "(`weight_schedule_speeds` in controller/tuning.toml). A setting without low-speed fields has "
           "the same weights at every speed.",
           ]
    out += [f"- Stage 1 of {sweep.controller} (no MPC weights: its own gains, {len(sweep.own_grid)} "
            f"settings; no stages 2-4): {_grid_text(sweep.own_grid)}."
            for sweep in sweeps if sweep.own_grid is not None]
    out += [f"- {key}: {value}" for key, value in context.items()]
    out += ["", "| controller | swept fields | evaluations | chosen setting | tuning-set e_Y RMSE (m) "
            "| before: setting, e_Y RMSE (m) | runs incomplete | s / evaluation |",
            "|---|---|---|---|---|---|---|---|"]
    for sweep in sweeps:
        chosen = sweep.chosen
        before = sweep.before
        before_text = ("not evaluated" if before is None
                       else f"{setting_text(before.setting)}: {before.objective_m:.4f}")
        incomplete = sum(not done for e in sweep.evaluations for done in e.completed.values())
        seconds = float(np.mean([e.seconds for e in sweep.evaluations]))
        out.append(f"| {sweep.controller} | {', '.join(sweep.weight_fields + sweep.observer_fields)} | "
                   f"{len(sweep.evaluations)} | {setting_text(chosen.setting)} | {chosen.objective_m:.4f} | "
                   f"{before_text} | {incomplete} of {len(sweep.evaluations) * len(names)} | {seconds:.1f} |")
    for sweep in sweeps:
        out += ["", f"#### {sweep.controller}", "",
                f"Stage 1: {_grid_text(sweep.own_grid or weight_grid)}"
                + (f"; stage 2: {_grid_text(observer_grid.restricted(sweep.observer_fields))}."
                   if sweep.observer_fields else "; no observer fields (no stage 2)."),
                "", f"Top {TOP_N} (chosen first):", "",
                "| rank | stage | setting | mean e_Y RMSE (m) | worst scenario e_Y RMSE (m) | incomplete runs |",
                "|---|---|---|---|---|---|"]
        for rank, evaluation in enumerate(sweep.top(), start=1):
            worst_name = max(evaluation.rmse_m, key=lambda n: (not evaluation.completed[n],
                                                              np.nan_to_num(evaluation.rmse_m[n], nan=np.inf)))
            incomplete = [n for n, done in evaluation.completed.items() if not done]
            out.append(f"| {rank} | {evaluation.stage} | {setting_text(evaluation.setting)} | "
                       f"{evaluation.objective_m:.4f} | {worst_name}: {evaluation.rmse_m[worst_name]:.4f} | "
                       f"{', '.join(incomplete) or '-'} |")
        chosen = sweep.chosen
        grid_levels = (dict((sweep.own_grid or weight_grid).levels) | dict(observer_grid.levels)
                       | dict(LOW_SPEED_GRID.levels))
        # Only fields with an interior level: with two levels every choice is an "edge".
        edges = [name for name, value in chosen.setting
                 if len(grid_levels.get(name, ())) > 2 and value in (min(grid_levels[name]), max(grid_levels[name]))]
        if edges:
            out += ["", f"The chosen {', '.join(edges)} {'is' if len(edges) == 1 else 'are'} at the "
                    "edge of the grid: a wider grid might find a better value."]
        out += ["", "Chosen setting per tuning scenario: "
                + "; ".join(f"{n} {chosen.rmse_m[n]:.4f} m" + ("" if chosen.completed[n] else " (incomplete)")
                            for n in names) + "."]
    out += ["", "The figures are tuning-set figures, for choosing settings: they rank settings of one "
            "controller and say nothing about how controllers compare on the evaluation "
            "(results/table2_high_mu.md, results/table3_low_mu.md)."]
    return "\n".join(out) + "\n"


def plot_sweep(sweeps: Sequence[ControllerSweep], path: Path) -> None:
    """Each controller's objectives sorted (log axis), the chosen setting (circle) and the
    setting before the sweep (cross at 0) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.0, 4.5))
    for sweep in sweeps:
        values = np.sort([min(e.objective_m, FAILURE_PENALTY_M) for e in sweep.evaluations])
        line, = ax.plot(np.arange(1, values.size + 1), values, marker=".", label=sweep.controller)
        ax.plot([1], [sweep.chosen.objective_m], marker="o", color=line.get_color(), markersize=8)
        if sweep.before is not None:
            ax.plot([0], [min(sweep.before.objective_m, FAILURE_PENALTY_M)], marker="x",
                    color=line.get_color(), markersize=8)
    ax.set_yscale("log")
    ax.set_xlabel("settings of the controller, best first (x at 0: the setting before the sweep)")
    ax.set_ylabel("mean e_Y RMSE on the tuning set (m, log)")
    ax.set_title("make tune: every setting's objective on the tuning set (circle: chosen)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def sweep_document(sweeps: Sequence[ControllerSweep], names: Sequence[str],
                   context: Mapping[str, str],
                   weight_grid: SweepGrid = WEIGHT_GRID, observer_grid: SweepGrid = OBSERVER_GRID,
                   observer_start: Setting = OBSERVER_START) -> dict[str, Any]:
    """The JSON document: procedure, context, and every evaluation per controller."""
    return {
        "generated_by": "make tune (python -m studies.tuning_sweep)",
        "scenarios": list(names),
        "objective": f"mean e_Y RMSE over the scenarios (m); {FAILURE_PENALTY_M:g} m for an incomplete run",
        "weight_grid": weight_grid.as_dict(), "observer_grid": observer_grid.as_dict(),
        "observer_start": dict(observer_start), "context": dict(context),
        "controllers": {
            sweep.controller: {
                "swept_fields": list(sweep.weight_fields + sweep.observer_fields),
                **({} if sweep.own_grid is None else {"own_grid": sweep.own_grid.as_dict()}),
                "before": None if sweep.before is None else sweep.before.as_dict(),
                "chosen": sweep.chosen.as_dict(),
                "evaluations": [e.as_dict() for e in sweep.evaluations],
            } for sweep in sweeps},
    }


def _evaluation_from_dict(entry: Mapping[str, Any]) -> Evaluation:
    return Evaluation(controller=entry["controller"], stage=entry["stage"],
                      setting=tuple((name, float(value)) for name, value in entry["setting"].items()),
                      rmse_m=dict(entry["rmse_m"]), max_abs_m=dict(entry["max_abs_m"]),
                      completed=dict(entry["completed"]), failure=dict(entry["failure"]),
                      objective_m=float(entry["objective_m"]), seconds=float(entry["seconds"]))


def _grid_from_dict(levels: Mapping[str, Sequence[float]]) -> SweepGrid:
    return SweepGrid(tuple((name, tuple(float(v) for v in values)) for name, values in levels.items()))


@dataclass(frozen=True)
class SweepRecord:
    """A sweep as :func:`sweep_document` stored it (``--report-from``)."""

    sweeps: list[ControllerSweep]
    names: list[str]
    context: dict[str, str]
    weight_grid: SweepGrid
    observer_grid: SweepGrid
    observer_start: Setting


def sweep_from_document(document: Mapping[str, Any]) -> SweepRecord:
    """Rebuild the sweep from its JSON document (the inverse of :func:`sweep_document`).

    Raises StudyError for a document that lacks a field."""
    try:
        sweeps = []
        for name, entry in document["controllers"].items():
            evaluations = tuple(_evaluation_from_dict(e) for e in entry["evaluations"])
            fields = tuple(entry["swept_fields"])
            sweeps.append(ControllerSweep(
                controller=name,
                weight_fields=tuple(f for f in fields if f not in OBSERVER_FIELDS),
                observer_fields=tuple(f for f in fields if f in OBSERVER_FIELDS),
                evaluations=evaluations, chosen=best(evaluations),
                before=None if entry.get("before") is None else _evaluation_from_dict(entry["before"]),
                own_grid=None if entry.get("own_grid") is None else _grid_from_dict(entry["own_grid"])))
        return SweepRecord(sweeps, list(document["scenarios"]), dict(document["context"]),
                           _grid_from_dict(document["weight_grid"]), _grid_from_dict(document["observer_grid"]),
                           tuple((k, float(v)) for k, v in document["observer_start"].items()))
    except (KeyError, TypeError, AttributeError) as e:
        raise StudyError(f"not a tuning sweep document: {e!r}") from e


def write_reports(record: SweepRecord, out: Path, *, document: bool = True) -> None:
    """``tuning_sweep.md`` and ``.png`` (and, with ``document``, ``.json``) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    grids = (record.weight_grid, record.observer_grid, record.observer_start)
    (out / "tuning_sweep.md").write_text(sweep_markdown(record.sweeps, record.names, record.context, *grids))
    if document:
        (out / "tuning_sweep.json").write_text(
            json.dumps(sweep_document(record.sweeps, record.names, record.context, *grids), indent=1) + "\n")
    plot_sweep(record.sweeps, out / "tuning_sweep.png")

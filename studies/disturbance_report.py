"""The disturbance study's report (``make disturbances``; docs/disturbances.md).

``python -m studies.disturbance_report GRID --campaign DIR --out OUT [--featured NAME]``
reads the cells of the campaign grid GRID (``studies/campaign/grids/disturbances.toml``:
every controller x {lane change, straight-curve-straight} x each disturbance at two sizes
and none) that ``python -m studies.campaign GRID --out DIR`` computed and cached in DIR,
and writes to OUT:

- ``disturbances.md``: per scenario, e_Y RMSE and the steady lateral offset on each of
  its straights (``studies.disturbance_offsets``) per disturbance and controller, then
  the figures the issue's goals ask for (ESO-DKMPC's steady offset as a share of DKMPC's
  under each constant disturbance, the lowest e_Y RMSE, ESO-DKMPC against DKMPC without a
  disturbance); figures only, no verdict on a controller;
- ``disturbances.csv`` and ``disturbances.json``: every cell (axes, outcome, e_Y RMSE and
  max, heading RMSE, offsets, wall time); the JSON also the straights and the run's facts;
- ``disturbances.png``: ``studies.disturbance_figure``.

Exit status 0, or 1 when the grid is bad or DIR holds none of its cells (run the campaign
first); cells still missing are named in the report's first lines.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from studies.disturbance_offsets import (MIN_TIME_ON_S, WINDOW_S, Straight, label_straights,
                                         steady_offset, straight_sections)

#: The files written to ``--out``.
OUTPUT_NAMES = ("disturbances.md", "disturbances.csv", "disturbances.json", "disturbances.png")
#: Below this |offset| (m) a ratio of offsets says nothing (both at the noise of the plant).
OFFSET_FLOOR_M = 0.001
#: Columns of disturbances.csv before the offsets (one column per straight label).
CSV_FIELDS = ("controller", "scenario", "disturbance", "completed", "end_reason", "e_y_rmse",
              "e_y_max", "heading_rmse", "wall_s", "error")


@dataclass(frozen=True)
class CellResult:
    """One cell's figures: e_Y RMSE / max (m), heading RMSE (rad), steady offsets (m) by
    straight label (None: the run did not settle there or did not complete)."""

    controller: str
    scenario: str
    disturbance: str
    completed: bool
    end_reason: str
    e_y_rmse: float
    e_y_max: float
    heading_rmse: float
    wall_s: float
    error: str
    offsets: Mapping[str, float | None]


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def scenario_straights(grid: Any, rows: Sequence[Mapping[str, Any]]) -> dict[str, list[Straight]]:
    """Per scenario of the grid, its straights on which some completed run settled."""
    from controller.reference import ReferencePath
    from hil.scenario import Scenario

    out: dict[str, list[Straight]] = {}
    for name, file in grid.scenario_files.items():
        path = ReferencePath.from_csv(Scenario.load(file).path_file)
        ranges = straight_sections(path.s, path.yaw)
        traces = [r["trace"] for r in rows if r["scenario"] == name and r.get("completed") and r.get("trace")]
        reached = [any(steady_offset(t, a, b) is not None for t in traces) for a, b in ranges]
        out[name] = label_straights(ranges, reached)
    return out


def cell_results(rows: Sequence[Mapping[str, Any]], straights: Mapping[str, Sequence[Straight]]) -> list[CellResult]:
    """The rows (campaign rows with their ``trace``) as :class:`CellResult`, grid order."""
    results = []
    for row in rows:
        completed = bool(row.get("completed"))
        trace = row.get("trace")
        offsets = {s.label: (steady_offset(trace, s.start_m, s.end_m) if completed and trace else None)
                   for s in straights[row["scenario"]]}
        results.append(CellResult(
            controller=row["controller"], scenario=row["scenario"], disturbance=row["disturbance"],
            completed=completed, end_reason=str(row.get("end_reason", "")),
            e_y_rmse=_number(row.get("e_y_rmse")), e_y_max=_number(row.get("e_y_max")),
            heading_rmse=_number(row.get("heading_rmse")), wall_s=_number(row.get("wall_s")),
            error=str(row.get("error", "")), offsets=offsets))
    return results


# ---------------------------------------------------------------------------- tables

def _cm(value: float | None, digits: int) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value * 100:.{digits}f}"


def _cell_text(result: CellResult | None, value: float | None, digits: int) -> str:
    if result is None:
        return "(missing)"
    if not result.completed:
        return f"({result.end_reason or 'error'})"
    return _cm(value, digits)


def _table(results: Sequence[CellResult], scenario: str, disturbances: Sequence[str],
           controllers: Sequence[str], value: Any, digits: int) -> list[str]:
    from studies.campaign.report import column_label

    by_key = {(r.disturbance, r.controller): r for r in results if r.scenario == scenario}
    lines = ["| disturbance | " + " | ".join(column_label(c) for c in controllers) + " |",
             "|---|" + "---|" * len(controllers)]
    for disturbance in disturbances:
        cells = []
        for controller in controllers:
            result = by_key.get((disturbance, controller))
            cells.append(_cell_text(result, None if result is None else value(result), digits))
        lines.append(f"| {disturbance} | " + " | ".join(cells) + " |")
    return lines


def _constant(grid: Any, disturbance: str) -> bool:
    """A disturbance that stays on (no gust), other than "none"."""
    table = grid.disturbances.get(disturbance, {})
    return bool(table) and not table.get("gust_force_n")


def goal_lines(grid: Any, results: Sequence[CellResult], straights: Mapping[str, Sequence[Straight]],
               disturbances: Sequence[str], controllers: Sequence[str]) -> list[str]:
    """Markdown: the figures the issue's goals name (ESO-DKMPC against DKMPC and the rest),
    where both controllers are in the grid; no lines otherwise."""
    from studies.campaign.report import column_label

    if not {"eso-dkmpc", "dkmpc"} <= set(controllers):
        return []
    lines = ["", "## Against the issue's goals", "",
             "Per constant disturbance (not the gusts) and straight: ESO-DKMPC's steady offset as a share "
             "of DKMPC's (the goal: at most 20 %; \"-\" where DKMPC's is below "
             f"{OFFSET_FLOOR_M * 1000:g} mm, or a run did not settle there), and the controller with the "
             "lowest e_Y RMSE of those that completed (the goal: ESO-DKMPC).", "",
             "| scenario | disturbance | straight | ESO-DKMPC offset (cm) | DKMPC offset (cm) | share | "
             "lowest e_Y RMSE | ESO-DKMPC's rank |", "|---|---|---|---|---|---|---|---|"]
    by_key = {(r.scenario, r.disturbance, r.controller): r for r in results}
    for scenario, sections in straights.items():
        for disturbance in disturbances:
            if not _constant(grid, disturbance):
                continue
            eso = by_key.get((scenario, disturbance, "eso-dkmpc"))
            dk = by_key.get((scenario, disturbance, "dkmpc"))
            ranked = sorted((r for r in results if r.scenario == scenario and r.disturbance == disturbance
                             and r.completed and math.isfinite(r.e_y_rmse)), key=lambda r: r.e_y_rmse)
            lowest = column_label(ranked[0].controller) if ranked else "-"
            rank = next((str(i + 1) for i, r in enumerate(ranked) if r.controller == "eso-dkmpc"), "-")
            for section in sections:
                a = eso.offsets.get(section.label) if eso else None
                b = dk.offsets.get(section.label) if dk else None
                share = (f"{abs(a) / abs(b) * 100:.0f} %" if a is not None and b is not None
                         and abs(b) >= OFFSET_FLOOR_M else "-")
                lines.append(f"| {scenario} | {disturbance} | {section.label} | {_cm(a, 2)} | {_cm(b, 2)} | "
                             f"{share} | {lowest} | {rank} of {len(ranked)} |")
    nominal = [(s, by_key.get((s, "none", "eso-dkmpc")), by_key.get((s, "none", "dkmpc"))) for s in straights]
    pairs = [(s, e, d) for s, e, d in nominal if e and d and e.completed and d.completed]
    if pairs:
        lines += ["", "Without a disturbance (the goal: ESO-DKMPC at most 1.02 x DKMPC's e_Y RMSE): "
                  + "; ".join(f"{s} {e.e_y_rmse * 100:.2f} / {d.e_y_rmse * 100:.2f} cm = "
                              f"{e.e_y_rmse / d.e_y_rmse:.3f}" for s, e, d in pairs) + "."]
    return lines


def markdown(grid: Any, results: Sequence[CellResult], straights: Mapping[str, Sequence[Straight]], *,
             command: str, campaign_dir: Path, missing: int) -> str:
    """``disturbances.md`` (see the module docstring)."""
    from hil.scenario import Scenario

    controllers = list(dict.fromkeys(c.controller for c in grid.cells))
    disturbances = list(dict.fromkeys(c.disturbance for c in grid.cells))
    done = sum(1 for r in results if r.completed)
    lines = [f"# Disturbance study (`{grid.name}`)", "", f"`{command}`", ""]
    if grid.description:
        lines += [grid.description, ""]
    lines += [
        f"- {len(results)} of {len(grid.cells)} cells in `{campaign_dir}`"
        + (f" ({missing} not computed yet: run the campaign again)" if missing else "")
        + f"; {done} completed (ran to the end, ECU ACTIVE, |e_Y| <= 2 m), the others show their end "
          "in brackets. Each cell is one lockstep run over CAN on the Python ECU (`python -m hil run "
          "--faults` of the cell's scenario, with its `[disturbances]` table: docs/plant.md).",
        f"- e_Y: the true pose's signed distance to the path at the control instants (+ = left). Steady "
        f"offset: the mean e_Y over the last {WINDOW_S:g} s the car spent on a straight of the path "
        f"(curvature below 1e-4 1/m), where it spent at least {MIN_TIME_ON_S:g} s "
        "(`studies/disturbance_offsets.py`); every disturbance pushes to the left (+y).",
        "",
    ]
    for scenario, sections in straights.items():
        description = Scenario.load(grid.scenario_files[scenario]).description
        where = ", ".join(f"{s.label} s = {s.start_m:.0f}-{s.end_m:.0f} m of the path" for s in sections)
        lines += [f"## {scenario}", "", f"{description}. Straights: {where or 'none the runs settled on'}.", "",
                  "e_Y RMSE (cm):", ""]
        lines += _table(results, scenario, disturbances, controllers, lambda r: r.e_y_rmse, 2)
        for section in sections:
            lines += ["", f"Steady lateral offset on the {section.label} (cm, mean e_Y over its last "
                          f"{WINDOW_S:g} s):", ""]
            lines += _table(results, scenario, disturbances, controllers,
                            lambda r, label=section.label: r.offsets.get(label), 2)
        lines += ["", "Largest |e_Y| (cm):", ""]
        lines += _table(results, scenario, disturbances, controllers, lambda r: r.e_y_max, 1)
        lines.append("")
    lines += goal_lines(grid, results, straights, disturbances, controllers)
    failures = [r for r in results if r.error]
    if failures:
        lines += ["", "## Cells that raised", "", "| controller | scenario | disturbance | error |", "|---|---|---|---|"]
        lines += [f"| {r.controller} | {r.scenario} | {r.disturbance} | {r.error[:160].replace('|', '/')} |"
                  for r in failures]
    return "\n".join(lines).rstrip("\n") + "\n"


# ---------------------------------------------------------------------------- files

def _labels(straights: Mapping[str, Sequence[Straight]]) -> list[str]:
    return list(dict.fromkeys(s.label for sections in straights.values() for s in sections))


def write_csv(path: Path, results: Sequence[CellResult], straights: Mapping[str, Sequence[Straight]]) -> Path:
    """``disturbances.csv``: :data:`CSV_FIELDS` then ``offset_<label>`` (m) per straight."""
    labels = _labels(straights)
    columns = [*CSV_FIELDS, *(f"offset_{label.replace(' ', '_')}" for label in labels)]
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(columns)
        for r in results:
            numbers = [r.e_y_rmse, r.e_y_max, r.heading_rmse]
            writer.writerow([r.controller, r.scenario, r.disturbance, int(r.completed), r.end_reason,
                             *("" if not math.isfinite(v) else f"{v:.6f}" for v in numbers),
                             "" if not math.isfinite(r.wall_s) else f"{r.wall_s:.1f}",
                             r.error.replace("\n", " "),
                             *("" if r.offsets.get(label) is None else f"{r.offsets[label]:.6f}"
                               for label in labels)])
    return path


def write_json(path: Path, grid: Any, results: Sequence[CellResult], straights: Mapping[str, Sequence[Straight]],
               *, command: str, machine: str) -> Path:
    """``disturbances.json``: the facts, the straights per scenario and every cell."""
    def clean(value: Any) -> Any:
        return None if isinstance(value, float) and not math.isfinite(value) else value

    document = {
        "command": command, "grid": grid.name, "cells_in_grid": len(grid.cells), "machine": machine,
        "window_s": WINDOW_S, "min_time_on_s": MIN_TIME_ON_S,
        "disturbances": {name: dict(table) for name, table in grid.disturbances.items()},
        "straights": {name: [asdict(s) for s in sections] for name, sections in straights.items()},
        "cells": [{k: clean(v) for k, v in asdict(r).items()} for r in results],
    }
    path.write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    return path


def write_report(grid: Any, rows: Sequence[Mapping[str, Any]], out: Path, *, command: str,
                 campaign_dir: Path, featured: str | None = None) -> list[Path]:
    """Write the four :data:`OUTPUT_NAMES` to ``out`` from the campaign ``rows`` (with their
    traces); returns the paths."""
    from studies.disturbance_figure import write_figure
    from studies.machine import machine_description

    straights = scenario_straights(grid, rows)
    results = cell_results(rows, straights)
    out.mkdir(parents=True, exist_ok=True)
    md = out / OUTPUT_NAMES[0]
    md.write_text(markdown(grid, results, straights, command=command, campaign_dir=campaign_dir,
                           missing=len(grid.cells) - len(rows)), encoding="utf-8")
    return [md, write_csv(out / OUTPUT_NAMES[1], results, straights),
            write_json(out / OUTPUT_NAMES[2], grid, results, straights, command=command,
                       machine=machine_description()),
            write_figure(out / OUTPUT_NAMES[3], grid, rows, results, straights, featured)]


def main(argv: Sequence[str] | None = None) -> int:
    """CLI (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m studies.disturbance_report",
                                     description="Report of the disturbance study from its campaign's cache.")
    parser.add_argument("grid", help="the campaign grid (a file, or a shipped grid's name: disturbances)")
    parser.add_argument("--campaign", type=Path, required=True,
                        help="the folder the campaign ran into (python -m studies.campaign GRID --out DIR)")
    parser.add_argument("--out", type=Path, required=True, help="folder for disturbances.{md,csv,json,png}")
    parser.add_argument("--featured", default=None,
                        help="the disturbance whose e_Y traces the figure shows (default: the largest "
                             "steering offset of the grid, else its first disturbance)")
    args = parser.parse_args(argv)
    from hil.errors import HilError
    from studies.campaign.grid import load_grid
    from studies.campaign.runner import cached_rows

    try:
        grid = load_grid(args.grid)
        if not (args.campaign / "cache").is_dir():
            raise HilError(f"--campaign {args.campaign}: no campaign there (run `python -m studies.campaign "
                           f"{args.grid} --out {args.campaign}` first)")
        rows = cached_rows(grid, args.campaign)
        if not rows:
            raise HilError(f"--campaign {args.campaign}: none of the {len(grid.cells)} cells of {grid.name} is "
                           "computed for this code (run the campaign first)")
        if args.featured is not None and args.featured not in grid.disturbances:
            raise HilError(f"--featured {args.featured!r}: not a disturbance of {grid.name} "
                           f"({', '.join(map(repr, grid.disturbances))})")
        command = "python -m studies.disturbance_report " + " ".join(
            shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        written = write_report(grid, rows, args.out, command=command, campaign_dir=args.campaign,
                               featured=args.featured)
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for path in written:
        print(f"wrote {path}")
    missing = len(grid.cells) - len(rows)
    print(f"{len(rows)} of {len(grid.cells)} cells" + (f", {missing} missing" if missing else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())

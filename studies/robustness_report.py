"""The robustness grid's report lines and output files (``make robustness``): the measured
ranking, issue 14's goal and what the observer adds, ``robustness.md``, ``robustness.csv``
and the heat maps of ``robustness.png``.
"""
from __future__ import annotations

import csv
import math
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from studies.machine import machine_description
from studies.robustness_cells import MANOEUVRES, MARGIN_S, SETTLE_M
from studies.robustness_records import CSV_FIELDS, LEAVE_ROAD_M, ROOT, RunRecord
from studies.robustness_summary import GridSummary, by_cell, summarise


# ---------------------------------------------------------------------------- report lines

def ranking_line(summary: GridSummary) -> str:
    """The measured ranking by mean e_Y RMSE over the common cells (lower first)."""
    from studies.report import display_name

    if not summary.common_cells:
        return "No cell was completed by every controller: no ranking."
    ordered = sorted(summary.rows, key=lambda row: row.common_rmse_mean)
    chain = " < ".join(f"{display_name(r.controller)} {r.common_rmse_mean:.4f} m" for r in ordered)
    most = max(row.lowest_count for row in summary.rows)
    leaders = [display_name(row.controller) for row in summary.rows if row.lowest_count == most]
    return (f"Measured ranking by mean e_Y RMSE over the {len(summary.common_cells)} cells every "
            f"controller completed (lower is better): {chain}. Lowest e_Y RMSE on the most of "
            f"those cells: {', '.join(leaders)} ({most} of {len(summary.common_cells)}"
            f"{' each' if len(leaders) > 1 else ''}).")


def goal_line(records: Sequence[RunRecord]) -> str | None:
    """Issue 14's goal on the grid, measured: on how many cells that at least one
    controller completed ESO-DKMPC completed with an e_Y RMSE at most LMPC's and NMPC's (a
    run that did not complete counts as an infinite RMSE). None without those three."""
    grouped = by_cell(records)
    names = ("eso-dkmpc", "lmpc", "nmpc")
    cells = [cell for cell, runs in grouped.items()
             if all(n in runs for n in names) and any(r.completed for r in runs.values())]
    if not cells:
        return None

    def rmse(run: RunRecord) -> float:
        return run.e_y_rmse if run.completed else math.inf

    met = sum(grouped[c]["eso-dkmpc"].completed
              and rmse(grouped[c]["eso-dkmpc"]) <= min(rmse(grouped[c]["lmpc"]), rmse(grouped[c]["nmpc"]))
              for c in cells)
    return (f"Issue 14's goal on the grid: ESO-DKMPC's e_Y RMSE at most LMPC's and NMPC's on "
            f"{met} of the {len(cells)} cells that at least one controller completed "
            f"({'met' if met * 2 > len(cells) else 'not met'}: \"most\" needs more than "
            f"{len(cells) // 2}; a run that did not complete counts as an infinite RMSE).")


@dataclass(frozen=True)
class HeadToHead:
    """ESO-DKMPC against DKMPC over ``cells`` cells that either completed: on ``wins`` its
    e_Y RMSE is lower, on ``losses`` DKMPC's (a run that did not complete counts as an
    infinite RMSE, a tie as neither)."""

    wins: int
    losses: int
    cells: int

    def text(self) -> str:
        return f"{self.wins} of {self.cells} (DKMPC lower on {self.losses})"


def is_mismatch(run: RunRecord) -> bool:
    """A model-mismatch cell: mass +300 kg or steering lag x3 (the learned model saw neither)."""
    return run.mass_offset_kg > 0.0 or run.lag_factor > 1.0


def observer_head_to_head(records: Sequence[RunRecord]) -> tuple[HeadToHead, HeadToHead] | None:
    """ESO-DKMPC against DKMPC on every cell either completed, and on its model-mismatch
    cells (:func:`is_mismatch`); None without both controllers."""
    grouped = by_cell(records)
    pairs = [(runs["eso-dkmpc"], runs["dkmpc"]) for runs in grouped.values()
             if "eso-dkmpc" in runs and "dkmpc" in runs and (runs["eso-dkmpc"].completed or runs["dkmpc"].completed)]
    if not pairs:
        return None

    def rmse(run: RunRecord) -> float:
        return run.e_y_rmse if run.completed else math.inf

    def count(selected: list[tuple[RunRecord, RunRecord]]) -> HeadToHead:
        return HeadToHead(sum(rmse(eso) < rmse(dk) for eso, dk in selected),
                          sum(rmse(eso) > rmse(dk) for eso, dk in selected), len(selected))

    return count(pairs), count([(eso, dk) for eso, dk in pairs if is_mismatch(eso)])


def observer_line(records: Sequence[RunRecord]) -> str | None:
    """What the observer adds on the grid (issue 35): :func:`observer_head_to_head` as a
    sentence; None without both controllers."""
    counts = observer_head_to_head(records)
    if counts is None:
        return None
    every, mismatch = counts
    return (f"The observer, head to head: ESO-DKMPC's e_Y RMSE below DKMPC's on {every.text()} of the "
            f"cells either completed; on the model-mismatch cells (mass +300 kg or steering lag x3) on "
            f"{mismatch.text()}.")


# ---------------------------------------------------------------------------- outputs

def write_csv(records: Sequence[RunRecord], file: Path) -> None:
    """``robustness.csv``: :data:`CSV_FIELDS`, one row per run."""
    with file.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_FIELDS, lineterminator="\n")
        writer.writeheader()
        for record in records:
            writer.writerow(record.csv_row())


def number_text(value: float, decimals: int = 4) -> str:
    """``value`` with ``decimals`` decimals; ``-`` when it is not finite (NaN: no cells)."""
    return "-" if not math.isfinite(value) else f"{value:.{decimals}f}"


def inputs_note(root: Path = ROOT) -> str:
    """Which commits the tuning file and the default model artefact come from (the last
    commit that changed each, and ``git log -1 -- models/artifacts/dk_d5.npz
    controller/tuning.toml`` for both), and whether the working tree changes them."""
    files = {"controller/tuning.toml": "tuning", "models/artifacts/dk_d5.npz": "artefact"}

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                              check=True, timeout=30).stdout

    try:
        last = {name: git("log", "-1", "--format=%h %s", "--", name).strip() for name in files}
        both = git("log", "-1", "--format=%h", "--", *files).strip()
        dirty = git("status", "--porcelain", "--", *files)
    except (OSError, subprocess.SubprocessError):
        return "tuning and artefact commits: unknown (no git)"
    parts = []
    for name, line in last.items():
        sha, _, subject = line.partition(" ")
        subject = subject if len(subject) <= 70 else subject[:67] + "..."
        parts.append(f"`{name}` of commit `{sha or '?'}` (\"{subject}\")")
    note = "; ".join(parts) + f" (last commit of either: `{both or '?'}`)"
    changed = [line[3:] for line in dirty.splitlines() if line.strip()]  # "XY path"
    if changed:
        note += ("; uncommitted changes to them in the working tree were used: "
                 + ", ".join(f"`{name}`" for name in changed))
    return note


def report_markdown(records: Sequence[RunRecord], summary: GridSummary, *, command: str,
                    inputs: str) -> str:
    """``robustness.md``."""
    from studies.report import display_name

    names = summary.controllers
    cells = summary.cells
    axes = {"manoeuvre": sorted({c.manoeuvre for c in cells}), "mu": sorted({c.mu for c in cells}),
            "speed (km/h)": sorted({c.speed_kmh for c in cells}),
            "mass offset (kg)": sorted({c.mass_offset_kg for c in cells}),
            "steering lag factor": sorted({c.lag_factor for c in cells})}
    run_seconds = sum(r.seconds for r in records)
    lines = [
        "# Robustness grid on our plant (`make robustness`)",
        "",
        f"`{command}`: every controller in closed loop with the four-wheel plant "
        "(`studies.closed_loop`, no CAN) on every cell of the grid, run by the campaign engine "
        "(`python -m studies.campaign`, runner `closed_loop`); see docs/robustness.md.",
        "",
        "- Grid: " + "; ".join(f"{axis} {' / '.join(f'{v:g}' if isinstance(v, float) else v for v in values)}"
                                 for axis, values in axes.items())
        + f": {len(cells)} cells per controller, {len(records)} runs.",
        f"- A run starts on the path at X = 0 at the target speed (held constant) and lasts "
        f"(end of the course + {SETTLE_M:g} m) / speed + {MARGIN_S:g} s; it is completed when "
        f"the runner does not stop it and max |e_Y| <= {LEAVE_ROAD_M:g} m (the road).",
        f"- Inputs: {inputs}.",
        f"- Machine: {machine_description()}; the runs took {run_seconds / 60:.1f} min of worker "
        "time in all (cached runs count their own run).",
        "",
        f"## (a) Per controller, over the {len(summary.common_cells)} cells every controller completed",
        "",
        "| controller | completed | " + " | ".join(f"{m} completed" for m in MANOEUVRES)
        + " | not run | mean e_Y RMSE (m) | median e_Y RMSE (m) | lowest e_Y RMSE (cells) |",
        "|---|---|" + "---|" * len(MANOEUVRES) + "---|---|---|---|",
    ]
    for row in summary.rows:
        per_manoeuvre = " | ".join(
            f"{row.completed_by_manoeuvre[m]} of {sum(1 for c in cells if c.manoeuvre == m)}"
            for m in MANOEUVRES)
        lines.append(f"| {display_name(row.controller)} | {row.completed} of {row.runs} | "
                     f"{per_manoeuvre} | {row.not_run} | {number_text(row.common_rmse_mean)} | "
                     f"{number_text(row.common_rmse_median)} | {row.lowest_count} of "
                     f"{len(summary.common_cells)} |")
    lines += [
        "",
        "Not run: the controller or the plant could not be built (`error` in robustness.csv). "
        "Lowest: the cells where the controller's e_Y RMSE is the smallest of all (ties count "
        "for each).",
        "",
        "## (b) e_Y RMSE (m) by mu x speed, over the cells every controller completed",
        "",
        "Mean over the other axes (manoeuvre, mass, steering lag) of the cells in the group "
        "that every controller completed; `cells` is how many.",
        "",
        "| mu | speed (km/h) | cells | " + " | ".join(display_name(n) for n in names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for (mu, speed), (count, values) in summary.pivot.items():
        best = min((v for v in values.values() if math.isfinite(v)), default=math.nan)
        shown = [(f"**{number_text(values[n])}**" if values[n] == best else number_text(values[n]))
                 for n in names]
        lines.append(f"| {mu:g} | {speed:g} | {count} | " + " | ".join(shown) + " |")
    lines += ["", "Bold: the lowest of the row.", "", "## (c) Ranking", "", ranking_line(summary)]
    goal = goal_line(records)
    if goal:
        lines += ["", goal]
    observer = observer_line(records)
    if observer:
        lines += ["", observer]
    lines += [
        "",
        f"## (d) Completed runs by mu x speed (of {summary.runs_per_group} per controller)",
        "",
        "| mu | speed (km/h) | " + " | ".join(display_name(n) for n in names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for (mu, speed), counts in summary.completed_pivot.items():
        lines.append(f"| {mu:g} | {speed:g} | " + " | ".join(str(counts[n]) for n in names) + " |")
    errors = [r for r in records if r.not_run]
    if errors:
        lines += ["", f"## Runs that could not be built ({len(errors)})", ""]
        lines += [f"- {display_name(r.controller)} on {r.cell.name}: {r.error}" for r in errors[:10]]
        if len(errors) > 10:
            lines.append(f"- ... and {len(errors) - 10} more (robustness.csv)")
    lines += ["", "Per run: robustness.csv. Figure: robustness.png.", ""]
    return "\n".join(lines)


def plot_heatmaps(records: Sequence[RunRecord], controllers: Sequence[str], file: Path,
                  mass_offset_kg: float = 0.0, lag_factor: float = 1.0) -> None:
    """``robustness.png``: one heat map of e_Y RMSE over mu (rows) x speed (columns) per
    controller (columns of panels) and manoeuvre (rows of panels), at ``mass_offset_kg``
    and ``lag_factor``; one logarithmic colour scale; a run not completed is a grey cell
    marked "off"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from studies.report import display_name

    chosen = [r for r in records
              if r.mass_offset_kg == mass_offset_kg and r.lag_factor == lag_factor]
    manoeuvres = [m for m in MANOEUVRES if any(r.manoeuvre == m for r in chosen)]
    mus = sorted({r.mu for r in chosen})
    speeds = sorted({r.speed_kmh for r in chosen})
    done = [r.e_y_rmse for r in chosen if r.completed and r.e_y_rmse > 0.0]
    low, high = (min(done), max(done)) if done else (1e-3, LEAVE_ROAD_M)
    norm = LogNorm(vmin=low, vmax=max(high, low * 1.01))
    figure, axes = plt.subplots(max(1, len(manoeuvres)), max(1, len(controllers)),
                                figsize=(2.6 * len(controllers) + 1.2, 2.6 * len(manoeuvres) + 1.0),
                                squeeze=False, constrained_layout=True)
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    image = None
    lookup = {(r.manoeuvre, r.controller, r.mu, r.speed_kmh): r for r in chosen}
    for i, manoeuvre in enumerate(manoeuvres):
        for j, name in enumerate(controllers):
            ax = axes[i][j]
            grid = np.full((len(mus), len(speeds)), np.nan)
            for a, mu in enumerate(mus):
                for b, speed in enumerate(speeds):
                    run = lookup.get((manoeuvre, name, mu, speed))
                    if run is not None and run.completed:
                        grid[a, b] = run.e_y_rmse
                    text = ("-" if run is None else f"{run.e_y_rmse:.3f}" if run.completed else "off")
                    ax.text(b, a, text, ha="center", va="center", fontsize=8,
                            color="black" if run is None or not run.completed
                            or norm(run.e_y_rmse) > 0.6 else "white")
            image = ax.imshow(np.ma.masked_invalid(grid), origin="lower", cmap=cmap, norm=norm,
                              aspect="auto")
            ax.set_xticks(range(len(speeds)), [f"{s:g}" for s in speeds])
            ax.set_yticks(range(len(mus)), [f"{m:g}" for m in mus])
            if i == len(manoeuvres) - 1:
                ax.set_xlabel("speed (km/h)")
            if j == 0:
                ax.set_ylabel(f"{manoeuvre}\nmu")
            if i == 0:
                ax.set_title(display_name(name))
    if image is not None:
        figure.colorbar(image, ax=axes, shrink=0.8, label="e_Y RMSE (m), log scale")
    figure.suptitle(f"e_Y RMSE (m) over mu x speed, mass {mass_offset_kg:+g} kg, steering lag "
                    f"x{lag_factor:g}\ngrey 'off': not completed (|e_Y| > {LEAVE_ROAD_M:g} m or "
                    "stopped)")
    figure.savefig(file, dpi=110)
    plt.close(figure)


def write_outputs(records: Sequence[RunRecord], controllers: Sequence[str], out: Path, *,
                  command: str) -> GridSummary:
    """Write ``robustness.md``, ``.csv`` and ``.png`` into ``out``; return the summary."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(records, controllers)
    write_csv(records, out / "robustness.csv")
    (out / "robustness.md").write_text(report_markdown(
        records, summary, command=command, inputs=inputs_note()))
    plot_heatmaps(records, controllers, out / "robustness.png")
    return summary



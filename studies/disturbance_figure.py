"""The disturbance study's figure, ``disturbances.png`` (``studies.disturbance_report``).

One column per scenario. Top: each controller's steady lateral offset on the scenario's
final straight (cm) under each disturbance, a group of bars per disturbance (a cross on
the axis where the run did not complete); for a scenario without a straight the runs
settled on (the lane change), its e_Y RMSE (cm) instead. Bottom: e_Y (cm) along the path (m of arc
length) of every controller under one disturbance (the featured one), the straights
shaded.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from studies.disturbance_offsets import Straight  # noqa: E402


def featured_disturbance(grid: Any, featured: str | None = None) -> str:
    """``featured``, else the grid's largest steering offset, else its first disturbance
    other than "none" (else "none")."""
    if featured is not None:
        return featured
    tables = grid.disturbances
    offsets = {name: abs(t.get("steer_offset_rad", 0.0)) for name, t in tables.items() if t}
    if offsets and max(offsets.values()) > 0.0:
        return max(offsets, key=offsets.get)
    return next((name for name, table in tables.items() if table), "none")


def _colour(controller: str, index: int) -> Any:
    from studies.report import COLOUR

    return COLOUR.get(controller, plt.get_cmap("tab10")(index % 10))


def write_figure(path: Path, grid: Any, rows: Sequence[Mapping[str, Any]], results: Sequence[Any],
                 straights: Mapping[str, Sequence[Straight]], featured: str | None = None) -> Path:
    """Write the figure (see the module docstring) to ``path``; returns it.

    Args:
        rows: the campaign rows (with ``trace``); results: their ``CellResult``s, same order.
    """
    from studies.campaign.report import column_label

    featured = featured_disturbance(grid, featured)
    controllers = list(dict.fromkeys(c.controller for c in grid.cells))
    disturbances = list(dict.fromkeys(c.disturbance for c in grid.cells))
    scenarios = list(straights)
    fig, axes = plt.subplots(2, len(scenarios), figsize=(7.5 * len(scenarios), 8.5), squeeze=False)
    width = 0.8 / max(1, len(controllers))
    by_key = {(r.scenario, r.disturbance, r.controller): r for r in results}
    for j, scenario in enumerate(scenarios):
        ax = axes[0, j]
        final = straights[scenario][-1].label if straights[scenario] else None
        for k, controller in enumerate(controllers):
            xs, heights, failed = [], [], []
            for i, disturbance in enumerate(disturbances):
                result = by_key.get((scenario, disturbance, controller))
                x = i - 0.4 + (k + 0.5) * width
                if result is not None and not result.completed:
                    failed.append(x)
                if result is None:
                    value = None
                elif final is None:  # no straight: the run's e_Y RMSE
                    value = result.e_y_rmse if result.completed else None
                else:
                    value = result.offsets.get(final)
                if value is not None:
                    xs.append(x)
                    heights.append(value * 100.0)
            ax.bar(xs, heights, width=width, color=_colour(controller, k), label=column_label(controller))
            if failed:
                ax.plot(failed, [0.0] * len(failed), "x", color=_colour(controller, k), markersize=7)
        ax.axhline(0.0, color="0.3", linewidth=0.6)
        ax.set_xticks(range(len(disturbances)), disturbances, rotation=40, ha="right", fontsize=7)
        what = f"steady lateral offset, {final}" if final else "e_Y RMSE (no straight)"
        ax.set_ylabel(f"{what} (cm)")
        ax.set_title(f"{scenario}: {what} (x: did not complete)", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        if j == 0:
            ax.legend(fontsize=7, ncol=2)

        ax = axes[1, j]
        for section in straights[scenario]:
            ax.axvspan(section.start_m, section.end_m, color="0.92", zorder=0)
        for k, controller in enumerate(controllers):
            row = next((r for r in rows if (r["scenario"], r["disturbance"], r["controller"])
                        == (scenario, featured, controller) and r.get("trace")), None)
            if row is None:
                continue
            trace = row["trace"]
            ax.plot(np.asarray(trace["progress"]), np.asarray(trace["e_y"]) * 100.0,
                    color=_colour(controller, k), linewidth=1.0, label=column_label(controller))
        ax.axhline(0.0, color="0.3", linewidth=0.6)
        ax.set_xlabel("path arc length (m); straights shaded")
        ax.set_ylabel("e_Y (cm, + left)")
        ax.set_title(f"{scenario}, {featured}: e_Y along the path", fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Disturbance study ({grid.name})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

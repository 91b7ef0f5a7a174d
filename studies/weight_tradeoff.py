"""Weights against road: every controller's Table II and Table III e_Y RMSE over the tuning
sweep's weight grid, to show what a fixed weighting trades between grip and the limit.

An analysis of the two evaluation scenarios, never a tuning: nothing here is chosen or
written into ``controller/tuning.toml`` (``make tune`` chooses on the tuning set alone).
Each controller runs both double lane changes (``dlc_high_mu``, ``dlc_low_mu``) at each of
the 36 MPC-weight settings of ``studies.tuning_sweep_grids.WEIGHT_GRID``; its other fields
(horizons, constraints, observer poles and decay) stay the tuning file's. The grid's
settings use their weights at every speed; the tuned weights, scheduled over speed
(``MpcTuning.weights_at``), are one more point, marked (a grid point when the tuned
schedule is flat).

What it reports, per controller:

- the tuned setting's pair (Table II, Table III e_Y RMSE) and its place on the front;
- the Pareto front: the settings that no other setting of the same controller beats on
  both roads (a run that does not complete counts ``FAILURE_PENALTY_M`` = 10 m);
- iso-robustness: the lowest Table II e_Y RMSE over the settings whose Table III e_Y RMSE
  is at most each of ``LOW_MU_LEVELS_M``, the comparison of controllers at equal
  behaviour on the low-mu road rather than at one weighting each.

Writes ``results/weight_tradeoff.{md,json,png}``. The runs are tasks of the campaigns'
executors (``studies.tuning_sweep_executor.SweepExecutor``): a local Ray with ``--workers``
CPUs, ``--address`` for a cluster, ``--workers 1`` in this process.

CLI: ``python -m studies.weight_tradeoff [--controllers ...] [--workers N] [--address ADDR]
[--out DIR] [--no-progress]``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from hil.errors import HilError
from hil.scenario import load_scenario
from studies.closed_loop import run_closed_loop
from controller.tuning import LOW_SPEED_WEIGHTS, SCHEDULED_WEIGHTS
from studies.tuning_sweep_executor import FAILURE_PENALTY_M, Evaluation, SweepExecutor, reuse_key
from studies.tuning_sweep_grids import WEIGHT_FIELDS, WEIGHT_GRID, Setting
from studies.tuning_sweep_procedure import current_setting

#: The evaluation scenarios of Tables II (high mu) and III (low mu), in that order.
SCENARIOS = ("dlc_high_mu", "dlc_low_mu")
#: Table III e_Y RMSE ceilings (m) of the iso-robustness table.
LOW_MU_LEVELS_M = (0.05, 0.1, 0.2)


@dataclass(frozen=True)
class Point:
    """One setting of one controller: its weights and the e_Y RMSE (m) on each road
    (``FAILURE_PENALTY_M`` for a run that did not complete)."""

    controller: str
    setting: Setting
    high_mu_m: float
    low_mu_m: float
    completed: tuple[bool, bool]
    tuned: bool

    @property
    def pair(self) -> tuple[float, float]:
        return self.high_mu_m, self.low_mu_m


def _penalised(evaluation: Evaluation, scenario: str) -> float:
    value = evaluation.rmse_m[scenario]
    ok = evaluation.completed[scenario] and math.isfinite(value)
    return value if ok else FAILURE_PENALTY_M


def pareto_front(points: Sequence[Point]) -> list[Point]:
    """The points no other point beats on both roads (ties kept), by Table II e_Y RMSE."""
    front = [p for p in points
             if not any(q.high_mu_m <= p.high_mu_m and q.low_mu_m <= p.low_mu_m and q.pair != p.pair
                        for q in points)]
    return sorted(front, key=lambda p: p.pair)


def best_high_mu_within(points: Sequence[Point], low_mu_max_m: float) -> Point | None:
    """The point with the lowest Table II e_Y RMSE among those with Table III e_Y RMSE at
    most ``low_mu_max_m`` (both runs completed); None when there is none."""
    eligible = [p for p in points if all(p.completed) and p.low_mu_m <= low_mu_max_m]
    return min(eligible, key=lambda p: p.pair, default=None)


def run_tradeoff(controllers: Sequence[str], tuning: Any, *, workers: int = 2, address: str | None = None,
                 show_progress: bool = True) -> dict[str, list[Point]]:
    """Every controller at every weight setting on both roads -> points per controller."""
    scenarios = [load_scenario(name) for name in SCENARIOS]
    jobs, tuned = [], {}
    for name in controllers:
        tuned[name] = tuple((f, v) for f, v in current_setting(tuning, name)
                            if f in WEIGHT_FIELDS + LOW_SPEED_WEIGHTS)
        grid = WEIGHT_GRID.settings()
        jobs += [(name, "weights", setting) for setting in grid]
        if all(reuse_key(setting) != reuse_key(tuned[name]) for setting in grid):
            jobs.append((name, "tuned", tuned[name]))  # scheduled, or flat off the grid
    with tqdm(total=len(jobs) * len(scenarios), desc="make tradeoff", unit="run",
              disable=not show_progress, dynamic_ncols=True) as progress:
        executor = SweepExecutor(scenarios, tuning, run_closed_loop, workers, progress, address)
        try:
            evaluations = executor.evaluate(jobs)
        finally:
            executor.close()
    points: dict[str, list[Point]] = {name: [] for name in controllers}
    for evaluation in evaluations:
        high, low = (_penalised(evaluation, s) for s in SCENARIOS)
        points[evaluation.controller].append(Point(
            evaluation.controller, evaluation.setting, high, low,
            tuple(bool(evaluation.completed[s]) for s in SCENARIOS),
            reuse_key(evaluation.setting) == reuse_key(tuned[evaluation.controller])))
    return points


def _weights_text(setting: Setting) -> str:
    """The weights but p_steer_rate (the normalisation); low-speed weights only where they
    differ from the others (a scheduled setting)."""
    named = dict(setting)
    shown = [(name, value) for name, value in setting
             if name in SCHEDULED_WEIGHTS
             or name in LOW_SPEED_WEIGHTS and value != named.get(name.removeprefix("low_speed_"))]
    return ", ".join(f"{name} {value:g}" for name, value in shown)


def _m(value: float) -> str:
    return "did not complete" if value >= FAILURE_PENALTY_M else f"{value:.4f}"


def markdown(points: Mapping[str, list[Point]], *, command: str, wall_s: float, workers: int) -> str:
    """The report (see the module docstring)."""
    from studies.report import display_name

    lines = [
        "### Weights against road: Table II vs Table III over the weight grid (`make tradeoff`)",
        "",
        f"Each controller at the {len(WEIGHT_GRID)} MPC-weight settings of the tuning sweep "
        f"(q_position x q_yaw x r_steer, p_steer_rate 300) on both double lane changes; observer "
        f"poles and decay as tuned; each setting's weights at every speed. **An analysis of the "
        f"evaluation scenarios, not a tuning**: the tuned weights (`make tune`, tuning set only), "
        f"scheduled over speed, are one more point of each controller, marked, and count among its "
        f"settings below (fronts, iso-robustness). A run that does "
        f"not complete counts {FAILURE_PENALTY_M:g} m. {command}: "
        f"{sum(len(v) for v in points.values()) * len(SCENARIOS)} runs in {wall_s / 60:.1f} min "
        f"on {workers} worker(s).",
        "",
        "| controller | tuned weights | tuned: Table II / III e_Y RMSE (m) | tuned on the front | "
        "lowest Table II over the grid (its Table III) | lowest Table III over the grid (its Table II) |",
        "|---|---|---|---|---|---|",
    ]
    for name, pts in points.items():
        tuned = next((p for p in pts if p.tuned), None)
        front = pareto_front(pts)
        low_high = min(pts, key=lambda p: p.pair)
        low_low = min(pts, key=lambda p: (p.low_mu_m, p.high_mu_m))
        tuned_text = "-" if tuned is None else f"{_m(tuned.high_mu_m)} / {_m(tuned.low_mu_m)}"
        on_front = "-" if tuned is None else ("yes" if tuned in front else "no")
        lines.append(f"| {display_name(name)} | {_weights_text(tuned.setting) if tuned else '-'} | "
                     f"{tuned_text} | {on_front} | {_m(low_high.high_mu_m)} ({_m(low_high.low_mu_m)}) | "
                     f"{_m(low_low.low_mu_m)} ({_m(low_low.high_mu_m)}) |")
    lines += ["", "Iso-robustness: the lowest Table II e_Y RMSE (m) among the settings whose Table III "
              "e_Y RMSE is at most the level (both runs completed); in brackets its Table III figure.",
              "", "| controller | " + " | ".join(f"Table III <= {level:g} m" for level in LOW_MU_LEVELS_M) + " |",
              "|---|" + "---|" * len(LOW_MU_LEVELS_M)]
    for name, pts in points.items():
        cells = []
        for level in LOW_MU_LEVELS_M:
            best = best_high_mu_within(pts, level)
            cells.append("none" if best is None else f"{best.high_mu_m:.4f} ({best.low_mu_m:.3f})")
        lines.append(f"| {display_name(name)} | " + " | ".join(cells) + " |")
    lines += ["", "Pareto fronts (settings no other setting of the same controller beats on both roads):", ""]
    for name, pts in points.items():
        front = pareto_front(pts)
        lines.append(f"- {display_name(name)}: " + "; ".join(
            f"{_weights_text(p.setting)} -> {_m(p.high_mu_m)} / {_m(p.low_mu_m)}" for p in front))
    lines += ["", "Figure: [weight_tradeoff.png](weight_tradeoff.png).", ""]
    return "\n".join(lines)


def plot(points: Mapping[str, list[Point]], file: Path) -> None:
    """Table II vs Table III e_Y RMSE per setting, fronts as lines, tuned points as stars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies.report import display_name

    fig, ax = plt.subplots(figsize=(8.5, 6.5))
    for index, (name, pts) in enumerate(points.items()):
        colour = f"C{index}"
        done = [p for p in pts if all(p.completed)]
        ax.scatter([p.high_mu_m for p in done], [p.low_mu_m for p in done], s=12, alpha=0.35, color=colour)
        front = [p for p in pareto_front(pts) if all(p.completed)]
        ax.plot([p.high_mu_m for p in front], [p.low_mu_m for p in front], "-o", ms=3, color=colour,
                label=f"{display_name(name)}: settings (dots), Pareto front (line)")
        for p in pts:
            if p.tuned and all(p.completed):
                ax.scatter([p.high_mu_m], [p.low_mu_m], marker="*", s=220, color=colour,
                           edgecolor="black", zorder=5)
    ax.scatter([], [], marker="*", s=150, color="white", edgecolor="black", label="tuned weights (make tune)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("Table II: e_Y RMSE on the high-mu double lane change (m)")
    ax.set_ylabel("Table III: e_Y RMSE on the low-mu double lane change (m)")
    ax.set_title("MPC weights trade grip against the limit: each controller over the tuning sweep's "
                 "weight grid\n(runs that do not complete are left out)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(file, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    from controller.registry import MPC_NAMES
    from controller.tuning import load_tuning

    parser = argparse.ArgumentParser(prog="python -m studies.weight_tradeoff", description=__doc__.splitlines()[0])
    # The MPCs only: the study sweeps eq. 15's weights, which a geometric baseline has not.
    parser.add_argument("--controllers", nargs="+", choices=MPC_NAMES, default=MPC_NAMES)
    parser.add_argument("--workers", type=int, default=2,
                        help="Ray workers (default 2; 1 runs in this process); on a cluster the most runs at once")
    parser.add_argument("--address", default=None, help="Ray cluster: auto, HOST:PORT or ray://HOST:PORT")
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    if not args.out.is_dir():
        print(f"error: {args.out}: no such folder", file=sys.stderr)
        return 1
    started = time.monotonic()
    try:
        points = run_tradeoff(args.controllers, load_tuning(), workers=args.workers, address=args.address,
                              show_progress=not args.no_progress)
    except HilError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    wall = time.monotonic() - started
    (args.out / "weight_tradeoff.md").write_text(
        markdown(points, command="make tradeoff", wall_s=wall, workers=args.workers), encoding="utf-8")
    (args.out / "weight_tradeoff.json").write_text(json.dumps(
        {name: [{"setting": dict(p.setting), "high_mu_m": p.high_mu_m, "low_mu_m": p.low_mu_m,
                 "completed": list(p.completed), "tuned": p.tuned} for p in pts]
         for name, pts in points.items()}, indent=1) + "\n", encoding="utf-8")
    plot(points, args.out / "weight_tradeoff.png")
    print(f"wrote {args.out}/weight_tradeoff.md, .json, .png ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    # Ray workers import the task function from studies.tuning_sweep_executor by name; run
    # the imported module's main so the classes compared here are the same ones.
    from studies.weight_tradeoff import main as _main

    sys.exit(_main())

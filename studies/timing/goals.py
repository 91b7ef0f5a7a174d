"""Repeated timing runs: their run-to-run spread and issue 37's goals with their verdicts.

The rows of `make timing` that are repeated (ESO-DKMPC, both ECUs, under each control-task
release of contract revision 3) form *groups*: one group per load condition, row label
("eso-dkmpc", "eso-dkmpc (C)") and release ("clock", "sample"). Each run gives one p99 per
figure; a group's spread is the min / median / max of those p99s over its runs. A goal is
met only when every run of its group meets it, and its line gives how many did and the
spread, so a single noisy run shows as such instead of being averaged away.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from studies.timing import report
from studies.timing.report import RunFigures, fmt_ms

#: Issue 37 (and issue 9 before it): RX-to-TX latency p99 of ESO-DKMPC in both ECUs, ms.
GOAL_LATENCY_P99_MS = 3.0
#: Issue 37: the Python ESO-DKMPC task time p99 with the machine idle, ms.
GOAL_TASK_P99_MS = 2.0
#: Issue 18 / 37: the C ECU's ESO-DKMPC task time p99, idle and under stress, ms.
GOAL_C_TASK_P99_MS = 0.25
#: Issue 9: ESO-DKMPC's task time p99 at most this multiple of LMPC's.
GOAL_LMPC_RATIO = 2.0
#: A run speaks for a goal only when the law ran (ACTIVE or DEGRADED) on at least this
#: share of its cycles: a controller that fell into SAFE_STOP has no overruns to count.
MIN_CONTROLLING_SHARE = 0.95
#: The modes in which the law runs, by name (as `RunFigures.modes` counts them).
CONTROLLING_MODES = tuple(mode.name for mode in report.CONTROLLING_MODES)
#: The figures whose p99 the spread table gives: (field, label).
SPREAD_FIGURES = (("rx_to_tx_latency", "RX-to-TX"), ("task_time", "task time"),
                  ("input_age", "input age"))
#: The ESO-DKMPC rows of the two ECUs: (row label, ECU named in the goal lines).
ESO_ROWS = (("eso-dkmpc", "Python"), ("eso-dkmpc (C)", "C"))

GroupKey = tuple[str, str, str]  # (condition, row label, release)


@dataclass(frozen=True)
class Spread:
    """min / median / max over the runs of one group (NaN runs left out; all NaN: NaN)."""

    low: float
    median: float
    high: float
    runs: int

    def describe(self) -> str:
        """``min / median / max`` in ms, 3 decimals; one value for a single run."""
        if self.runs == 1:
            return fmt_ms(self.median)
        return f"{fmt_ms(self.low)} / {fmt_ms(self.median)} / {fmt_ms(self.high)}"


def spread(values: list[float]) -> Spread:
    """The `Spread` of ``values`` (one figure per run, shape (runs,)).

    Raises:
        ValueError: ``values`` is empty.
    """
    if not values:
        raise ValueError("spread of no runs: a group has at least one run")
    finite = np.asarray([v for v in values if np.isfinite(v)], dtype=float)
    if not finite.size:
        return Spread(float("nan"), float("nan"), float("nan"), len(values))
    return Spread(float(finite.min()), float(np.median(finite)), float(finite.max()), len(values))


def group_runs(figures: list[RunFigures]) -> dict[GroupKey, list[RunFigures]]:
    """The runs by (condition, row label, release), in the order first seen."""
    groups: dict[GroupKey, list[RunFigures]] = {}
    for f in figures:
        groups.setdefault((f.condition, f.controller, f.release), []).append(f)
    return groups


def p99_spread(runs: list[RunFigures], field: str) -> Spread:
    """The spread of the p99 of ``field`` over ``runs``."""
    return spread([f.stats[field][1] for f in runs])


def spread_table(figures: list[RunFigures], min_runs: int = 2) -> list[str]:
    """Markdown: per group of at least ``min_runs`` runs the p99 min / median / max of
    `SPREAD_FIGURES` and the overruns of every run."""
    header = " | ".join(f"{label} p99 min / median / max (ms)" for _, label in SPREAD_FIGURES)
    lines = [f"| load | controller | release | runs | {header} | overruns at 25 ms per run |",
             "|---|---|---|---|" + "---|" * len(SPREAD_FIGURES) + "---|"]
    for (condition, controller, release), runs in group_runs(figures).items():
        if len(runs) < min_runs:
            continue
        cells = " | ".join(p99_spread(runs, field).describe() for field, _ in SPREAD_FIGURES)
        lines.append(f"| {condition} | {controller} | {release} | {len(runs)} | {cells} "
                     f"| {', '.join(str(f.overruns) for f in runs)} |")
    return lines


def law_idle(runs: list[RunFigures]) -> str | None:
    """Why ``runs`` cannot speak for a goal (the law ran on too few cycles of a run), or
    None when it ran on at least `MIN_CONTROLLING_SHARE` of every run's cycles."""
    for f in runs:
        ran = sum(f.modes.get(mode, 0) for mode in CONTROLLING_MODES)
        if f.cycles == 0 or ran < MIN_CONTROLLING_SHARE * f.cycles:
            others = ", ".join(f"{mode} {n}" for mode, n in f.modes.items() if mode not in CONTROLLING_MODES)
            return (f"the law ran on {ran} of {f.cycles} cycles of run {f.repeat}"
                    + (f" ({others})" if others else ""))
    return None


def _verdict(runs: list[RunFigures], field: str, limit_ms: float) -> str:
    """``met (n of n runs), p99 ...`` or ``NOT met (k of n runs within), p99 ...``; NOT met
    whenever the law did not run (`law_idle`)."""
    values = [f.stats[field][1] for f in runs]
    within = sum(1 for v in values if np.isfinite(v) and v <= limit_ms)
    idle = law_idle(runs)
    word = "met" if within == len(values) and idle is None else "NOT met"
    if idle is not None:
        word += f" ({idle})"
    figure = spread(values)
    measured = (f"p99 {figure.describe()} ms" if len(values) == 1 else
                f"p99 min / median / max {figure.describe()} ms")
    return f"{word} ({within} of {len(values)} run{'s' if len(values) > 1 else ''} within), {measured}"


def goal_lines(figures: list[RunFigures]) -> list[str]:
    """Issue 37's goals, per load condition and release, each ``met`` / ``NOT met`` with the
    measured figure: ESO-DKMPC's RX-to-TX latency p99 (both ECUs), the C ECU's task p99, the
    Python task p99 (idle only, as the issue states it), the ESO-DKMPC / LMPC task ratio of
    issue 9 (where LMPC ran under the same release) and the overruns of every row."""
    groups = group_runs(figures)
    lines: list[str] = []
    for condition in dict.fromkeys(f.condition for f in figures):
        for release in dict.fromkeys(f.release for f in figures if f.condition == condition):
            where = f"{condition}, {release} release"
            for row, ecu in ESO_ROWS:
                runs = groups.get((condition, row, release))
                if not runs:
                    continue
                lines.append(f"- {where}: ESO-DKMPC ({ecu} ECU) RX-to-TX latency p99 <= "
                             f"{GOAL_LATENCY_P99_MS:g} ms: "
                             f"{_verdict(runs, 'rx_to_tx_latency', GOAL_LATENCY_P99_MS)}")
                limit = GOAL_C_TASK_P99_MS if ecu == "C" else \
                    (GOAL_TASK_P99_MS if condition == "idle" else None)
                if limit is not None:
                    lines.append(f"- {where}: ESO-DKMPC ({ecu} ECU) task time p99 <= {limit:g} ms: "
                                 f"{_verdict(runs, 'task_time', limit)}")
            eso, lmpc = groups.get((condition, "eso-dkmpc", release)), \
                groups.get((condition, "lmpc", release))
            if eso and lmpc:
                ratio = p99_spread(eso, "task_time").median / p99_spread(lmpc, "task_time").median
                lines.append(f"- {where}: ESO-DKMPC / LMPC task time p99 (medians over the runs) = "
                             f"{ratio:.2f} (<= {GOAL_LMPC_RATIO:g}): "
                             f"{'met' if ratio <= GOAL_LMPC_RATIO else 'NOT met'}")
            for (group_condition, row, group_release), runs in groups.items():
                if (group_condition, group_release) != (condition, release):
                    continue
                overruns = [f.overruns for f in runs]
                seconds = ", ".join(dict.fromkeys(f"{f.seconds:g}" for f in runs))
                idle = law_idle(runs)
                verdict = "met" if not any(overruns) and idle is None else "NOT met"
                lines.append(f"- {where}: {row} overruns at 25 ms (goal 0): "
                             f"{', '.join(map(str, overruns))} in {len(runs)} run"
                             f"{'s' if len(runs) > 1 else ''} of {seconds} s: "
                             f"{verdict}{f' ({idle})' if idle else ''}; commands lost: "
                             f"{', '.join(str(f.commands_lost) for f in runs)}")
    return lines

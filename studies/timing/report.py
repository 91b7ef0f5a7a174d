"""Figures of timing runs: the measurement window, percentiles, goals, tables, histograms.

A run's window is from ``SETTLE_S`` after the plant started (the ECU engages in its first
cycles; the first control step sets the controller up) to the plant's end, on the
CLOCK_MONOTONIC stamps that the ECU's timing record (``start_time``) and the plant
process share. Cycles outside it (ECU waiting for the plant, plant gone) are left out of
the percentiles; overruns are counted from the plant's start itself.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from can_defs.frames import CtrlMode

from firmware_sim.config import NS_PER_MS, SAMPLE_WATCHDOG_NS
from studies.timing.runner import TimingRun

SETTLE_S = 1.0
PERIOD_MS = 25.0
#: Figures from the ECU's record, in report order: (field, label).
FIGURES = (("release_jitter", "release jitter"), ("task_time", "task time"),
           ("solve_time", "solver time"), ("input_age", "input age"),
           ("rx_to_tx_latency", "RX-to-TX latency"))
QUANTILES = (50.0, 99.0, 99.9)
#: Lower end of the log-spaced histogram bins, ms.
HISTOGRAM_FLOOR_MS = 0.01
#: CTRL_MODE values in which the controller runs.
CONTROLLING_MODES = (CtrlMode.ACTIVE, CtrlMode.DEGRADED)
_MODE_NAMES = {int(mode): mode.name for mode in CtrlMode}


@dataclass(frozen=True)
class RunFigures:
    """What one run measured in its window. Times in ms; ``stats[field]`` = (p50, p99,
    p99.9, max, n). ``release``: the ECU's control-task release (clock: contract revision 2;
    sample: revision 3); ``repeat``: the run's number among the repeats of its row (1-based)."""

    condition: str
    controller: str
    seconds: float
    cycles: int
    modes: dict[str, int]
    overruns: int
    commands_received: int
    commands_lost: int
    command_e2e_errors: int
    plant_commands_rejected: int
    command_gap_max_ms: float
    plant_tick_overruns: int
    plant_ticks: int
    lateral_error_max_m: float
    steal_share: float
    stats: dict[str, tuple[float, float, float, float, int]]
    samples_ms: dict[str, np.ndarray]
    scheduling: dict[str, str]
    release: str = "clock"
    repeat: int = 1
    #: Sample release: cycles released by the period watchdog (no good sample in the
    #: instant's window); None with the clock release, which has no watchdog.
    watchdog_releases: int | None = None


def _stats(values_ms: np.ndarray) -> tuple[float, float, float, float, int]:
    values_ms = values_ms[np.isfinite(values_ms)]
    if not values_ms.size:
        return (float("nan"),) * 4 + (0,)
    p50, p99, p999 = np.percentile(values_ms, QUANTILES)
    return float(p50), float(p99), float(p999), float(values_ms.max()), int(values_ms.size)


def watchdog_releases(release_jitter_s: np.ndarray) -> int:
    """Cycles of a sample-released run that the period watchdog released: their release
    comes SAMPLE_WATCHDOG_NS or more after its control instant (a sample releases inside
    the window, earlier). ``release_jitter_s``: (cycles,) release minus instant, s."""
    return int(np.count_nonzero(release_jitter_s * 1e3 >= SAMPLE_WATCHDOG_NS / NS_PER_MS))


def run_figures(run: TimingRun, condition: str, settle_s: float = SETTLE_S,
                repeat: int = 1) -> RunFigures:
    """The figures of ``run`` over its window (module docstring); ``repeat``: its number
    among the repeats of its row."""
    columns = run.ecu.columns
    start = columns["start_time"]
    t0, t1 = run.plant["started"] + settle_s, run.plant["ended"]
    window = (start >= t0) & (start <= t1)
    # Overruns from the plant's start on: the engagement and the controller's first step
    # (its set-up) must meet the deadline too.
    overruns = columns["overruns"]
    running = (start >= run.plant["started"]) & (start <= t1)
    before = overruns[start < run.plant["started"]]
    overruns_in_window = int(overruns[running].max() - (before.max() if before.size else 0)) \
        if running.any() else 0
    modes = {_MODE_NAMES.get(int(m), str(int(m))): int(n)
             for m, n in zip(*np.unique(columns["mode"][window], return_counts=True))}
    commands = run.plant["commands"]
    arrivals = np.asarray(commands["arrivals"], dtype=float)
    in_window = arrivals[(arrivals >= t0) & (arrivals <= t1)]
    gaps = np.diff(in_window) * 1e3
    samples = {name: columns[name][window] * 1e3 for name, _ in FIGURES}
    # the solver runs only while the controller does (ACTIVE, DEGRADED): elsewhere its
    # figure is 0 by definition and would only dilute the percentiles
    controlling = window & np.isin(columns["mode"], CONTROLLING_MODES)
    samples["solve_time"] = columns["solve_time"][controlling] * 1e3
    return RunFigures(
        condition=condition, controller=run.controller, seconds=run.seconds,
        cycles=int(window.sum()), modes=modes, overruns=overruns_in_window,
        commands_received=int(commands["received"]), commands_lost=int(commands["lost"]),
        command_e2e_errors=int(commands.get("e2e_errors", 0)),
        plant_commands_rejected=int(run.plant["plant_commands_rejected"]),
        command_gap_max_ms=float(gaps.max()) if gaps.size else float("nan"),
        plant_tick_overruns=int(run.plant["tick_overruns"]), plant_ticks=int(run.plant["ticks"]),
        lateral_error_max_m=float(run.plant["tracking"]["lateral_error_m"]["max_abs"]),
        steal_share=float(run.plant.get("steal_share", float("nan"))),
        stats={name: _stats(values) for name, values in samples.items()},
        samples_ms=samples, scheduling=dict(run.scheduling), release=run.release, repeat=repeat,
        watchdog_releases=(watchdog_releases(columns["release_jitter"][window]) if run.release == "sample"
                           else None))


def fmt_ms(value: float) -> str:
    """A figure in ms with 3 decimals, ``-`` where there is none (NaN)."""
    return "-" if not np.isfinite(value) else f"{value:.3f}"


def summary_table(figures: list[RunFigures]) -> list[str]:
    """Markdown: one row per run with the deadline and loss figures."""
    lines = ["| load | controller | release | run | s | cycles (ACTIVE) | overruns at 25 ms "
             "| commands lost | largest command gap at the plant (ms) | task p99 (ms) | RX-to-TX p99 (ms) "
             "| plant ticks late | CPU steal by the host | max abs e_Y (m) | watchdog releases |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for f in figures:
        lines.append(
            f"| {f.condition} | {f.controller} | {f.release} | {f.repeat} | {f.seconds:g} "
            f"| {f.cycles} ({f.modes.get('ACTIVE', 0)}) | {f.overruns} | {f.commands_lost} "
            f"| {fmt_ms(f.command_gap_max_ms)} | {fmt_ms(f.stats['task_time'][1])} "
            f"| {fmt_ms(f.stats['rx_to_tx_latency'][1])} | {f.plant_tick_overruns} of "
            f"{f.plant_ticks} | {100 * f.steal_share:.1f} % | {f.lateral_error_max_m:.3f} "
            f"| {'-' if f.watchdog_releases is None else f.watchdog_releases} |")
    return lines


def percentile_table(figures: list[RunFigures]) -> list[str]:
    """Markdown: p50 / p99 / p99.9 / max (ms) of every figure of every run."""
    lines = ["| load | controller | release | run | figure | n | p50 | p99 | p99.9 | max |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for f in figures:
        for name, label in FIGURES:
            p50, p99, p999, peak, n = f.stats[name]
            lines.append(f"| {f.condition} | {f.controller} | {f.release} | {f.repeat} "
                         f"| {label} | {n} | {fmt_ms(p50)} | {fmt_ms(p99)} | {fmt_ms(p999)} | {fmt_ms(peak)} |")
    return lines


def plot_histograms(figures: list[RunFigures], condition: str, out: Path) -> Path:
    """`histogram_figure` of one load condition to the PNG ``out``."""
    fig = histogram_figure(figures, condition)  # selects the Agg backend first
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def histogram_figure(figures: list[RunFigures], condition: str) -> Any:
    """The figure of one load condition: histograms of the figures on log-spaced bins (so that
    the QP controllers' ~2 ms and NMPC's ~25 ms both show), log counts, controllers
    overlaid, the 25 ms period dashed; every panel titled, one legend for every line (the
    dashed period included) in the sixth panel. The repeats of a row are pooled into one
    line; a line names its release where the condition's runs used more than one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [f for f in figures if f.condition == condition]
    several = len({f.release for f in runs}) > 1
    rows: dict[str, list[RunFigures]] = {}  # line label -> the runs pooled into it
    for f in runs:
        rows.setdefault(f"{f.controller}, {f.release} release" if several else f.controller,
                        []).append(f)
    fig, axes = plt.subplots(2, 3, figsize=(13.0, 6.5))
    flat = axes.ravel()
    legend: dict[str, Any] = {}  # label -> line, over all panels
    for ax, (name, label) in zip(flat, FIGURES):
        pooled = [np.concatenate([f.samples_ms[name] for f in row]) for row in rows.values()]
        finite = [v[np.isfinite(v)] for v in pooled]
        top = max((v.max() for v in finite if v.size), default=1.0)
        bins = np.geomspace(HISTOGRAM_FLOOR_MS, max(top * 1.1, 10 * HISTOGRAM_FLOOR_MS), 80)
        for row_label, values in zip(rows, finite):
            if values.size:
                ax.hist(np.maximum(values, HISTOGRAM_FLOOR_MS), bins=bins, histtype="step",
                        label=row_label, log=True)
        ax.set_xscale("log")
        if top >= 0.5 * PERIOD_MS:
            ax.axvline(PERIOD_MS, color="k", lw=0.8, ls="--",
                       label=f"control period {PERIOD_MS:g} ms (deadline)")
        ax.set_title(label)
        ax.set_xlabel(f"{label} [ms, log scale]")
        ax.set_ylabel("control cycles [count, log scale]")
        for handle, name in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(name, handle)
    # One legend for all panels, in the sixth (empty) one: every line drawn, the dashed
    # deadline included.
    flat[-1].legend(list(legend.values()), list(legend.keys()), loc="center",
                    title="lines (all panels)")
    flat[-1].axis("off")
    fig.suptitle(f"ECU timing per control cycle, {condition} (a row's repeated runs pooled; "
                 f"values below {HISTOGRAM_FLOOR_MS} ms in the first bin)")
    fig.tight_layout()
    return fig


def as_json(figures: list[RunFigures]) -> list[dict[str, Any]]:
    """JSON-ready figures (no samples)."""
    keys = ("condition", "controller", "release", "repeat", "seconds", "cycles", "modes",
            "overruns", "commands_received", "commands_lost", "command_e2e_errors",
            "plant_commands_rejected", "command_gap_max_ms", "plant_tick_overruns",
            "plant_ticks", "lateral_error_max_m", "steal_share", "scheduling", "watchdog_releases")
    out = []
    for f in figures:
        record = {key: getattr(f, key) for key in keys}
        record["stats_ms"] = {name: dict(zip(("p50", "p99", "p99.9", "max", "n"), values))
                              for name, values in f.stats.items()}
        out.append(record)
    return out

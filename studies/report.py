"""Tables (markdown) and figures (matplotlib, Agg) of the double-lane-change study.

Works from the plain per-run summaries of ``studies.paper_tables`` (the dicts written to
``results/study_metrics.json``) and, for figures, the traces of ``studies.closed_loop``.
The paper's CarSim/Simulink figures are printed beside ours for reference only: different
plant, different tuning, so the comparison is of trends, not of values.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from studies.closed_loop import ClosedLoopTrace  # noqa: E402

#: Paper Tables II and III (CarSim/Simulink): controller -> (e_Y Max/Avg/RMSE in m,
#: heading error Max/Avg/RMSE in rad).
PAPER_TRACKING: dict[str, dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]]] = {
    "dlc_high_mu": {
        "lmpc": ((0.606, 0.136, 0.225), (0.104, 0.025, 0.039)),
        "nmpc": ((0.619, 0.167, 0.229), (0.106, 0.025, 0.034)),
        "dkmpc": ((0.493, 0.123, 0.180), (0.026, 0.006, 0.010)),
        "eso-dkmpc": ((0.217, 0.066, 0.093), (0.042, 0.012, 0.017)),
    },
    "dlc_low_mu": {
        "lmpc": ((1.752, 0.345, 0.498), (0.416, 0.064, 0.104)),
        "nmpc": ((1.174, 0.342, 0.444), (0.150, 0.034, 0.054)),
        "dkmpc": ((0.521, 0.158, 0.210), (0.133, 0.035, 0.053)),
        "eso-dkmpc": ((0.686, 0.107, 0.198), (0.063, 0.014, 0.023)),
    },
}

#: Display names and colours, fixed per controller so every figure reads alike.
DISPLAY_NAME = {"eso-dkmpc": "ESO-DKMPC", "dkmpc": "DKMPC", "lmpc": "LMPC", "nmpc": "NMPC",
                "lmpc-eso": "LMPC-ESO", "dmdc-eso": "DMDc-ESO", "stanley": "Stanley"}
COLOUR = {"eso-dkmpc": "tab:red", "dkmpc": "tab:blue", "lmpc": "tab:green", "nmpc": "tab:orange",
          "lmpc-eso": "tab:olive", "dmdc-eso": "tab:purple", "stanley": "tab:gray"}
#: The ablations (issue 14 item 6): dashed in figures, explained under the tables.
ABLATION_NOTES = {
    "lmpc-eso": "LMPC-ESO = LMPC + ESO-DKMPC's observer on the bicycle's [vy, yaw rate] (no lift)",
    "dmdc-eso": "DMDc-ESO = ESO-DKMPC on a least-squares linear model z = x (no lift)",
}


def display_name(controller: str) -> str:
    return DISPLAY_NAME.get(controller, controller)


def _triple(values: Sequence[float]) -> str:
    return " / ".join(f"{v:.3f}" for v in values)


def tracking_table(title: str, runs: Sequence[Mapping[str, Any]], scenario: str) -> str:
    """Markdown table in the layout of the paper's Tables II / III.

    Args:
        title: heading line.
        runs: per-run summaries (``studies.paper_tables.run_summary``) of one scenario.
        scenario: scenario name, to look up the paper's values.
    """
    paper = PAPER_TRACKING.get(scenario, {})
    lines = [
        f"### {title}",
        "",
        "| controller | completed | e_Y (m) Max / Avg / RMSE | heading error (rad) Max / Avg / RMSE "
        "| paper e_Y (m) | paper heading (rad) |",
        "|---|---|---|---|---|---|",
    ]
    for run in runs:
        name = run["controller"]
        if run.get("error"):
            ours = ("not run", "-", "-")
        else:
            tracking = run["tracking"]
            lateral = tracking["lateral_error_m"]
            heading = tracking["heading_error_rad"]
            completed = "yes" if run["completed"] else f"no: {run['failure']}"
            ours = (completed,
                    _triple((lateral["max_abs"], lateral["mean_abs"], lateral["rmse"])),
                    _triple((heading["max_abs"], heading["mean_abs"], heading["rmse"])))
        paper_row = paper.get(name)
        paper_cells = (_triple(paper_row[0]), _triple(paper_row[1])) if paper_row else ("-", "-")
        lines.append(f"| {display_name(name)} | {' | '.join(ours)} | {' | '.join(paper_cells)} |")
    lines += [
        "",
        "Max = max |.|, Avg = mean |.|, RMSE over every 25 ms control step of the run. "
        "Columns 'paper' are the paper's CarSim/Simulink figures, for reference only "
        "(different plant and tuning).",
    ]
    ablations = [ABLATION_NOTES[n] for n in dict.fromkeys(r["controller"] for r in runs) if n in ABLATION_NOTES]
    if ablations:
        lines += ["", f"Ablations (docs/controllers.md): {'; '.join(ablations)}. Their tuning: "
                      "the tables of the same names in controller/tuning.toml."]
    not_run = [r for r in runs if r.get("error")]
    for run in not_run:
        lines.append(f"\n{display_name(run['controller'])} could not be built: {run['error']}")
    return "\n".join(lines) + "\n"


def plot_scenario(traces: Mapping[str, ClosedLoopTrace], path_xy: np.ndarray, title: str,
                  file: Path) -> None:
    """The paper's Fig. 8 / 9 panels plus e_Y over X, one line per controller.

    Args:
        traces: controller name -> its run's trace.
        path_xy: reference path points ``[x, y]``, shape (m, 2).
        title: figure title.
        file: PNG to write.
    """
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), constrained_layout=True)
    ax_speed, ax_steer, ax_path, ax_error = axes.ravel()
    first = next(iter(traces.values()), None)
    if first is not None:
        ax_speed.plot(first.time_s, first.target_speed * 3.6, "k--", lw=1.2, label="target")
    x_lo, x_hi = np.inf, -np.inf
    for name, trace in traces.items():
        style = {"color": COLOUR.get(name), "lw": 1.3, "label": display_name(name),
                 "ls": "--" if name in ABLATION_NOTES else "-"}
        ax_speed.plot(trace.time_s, trace.vx * 3.6, **style)
        ax_steer.plot(trace.time_s, trace.steer_angle, **style)
        ax_path.plot(trace.x, trace.y, **style)
        ax_error.plot(trace.x, trace.lateral_error, **style)
        x_lo, x_hi = min(x_lo, trace.x.min()), max(x_hi, trace.x.max())
    shown = (path_xy[:, 0] >= x_lo - 5) & (path_xy[:, 0] <= x_hi + 5) if np.isfinite(x_lo) \
        else np.ones(len(path_xy), bool)
    ax_path.plot(path_xy[shown, 0], path_xy[shown, 1], "k--", lw=1.2, label="reference")
    ax_error.axhline(0.0, color="k", lw=0.8)
    labels = [
        (ax_speed, "(a) longitudinal velocity", "time (s)", "Vx (km/h)"),
        (ax_steer, "(b) front wheel steering angle (measured)", "time (s)", "steer (rad)"),
        (ax_path, "(c) trajectory", "X (m)", "Y (m)"),
        (ax_error, "(d) lateral deviation e_Y (left positive)", "X (m)", "e_Y (m)"),
    ]
    for ax, panel, xlabel, ylabel in labels:
        ax.set_title(panel, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
    if traces:
        ax_speed.legend(fontsize=8)
        ax_path.legend(fontsize=8)
    else:
        ax_path.text(0.5, 0.5, "no run completed a single step", transform=ax_path.transAxes,
                     ha="center")
    fig.suptitle(title)
    fig.savefig(file, dpi=110)
    plt.close(fig)

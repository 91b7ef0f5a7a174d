"""Seeds of one training at a glance: ``studies.model_fidelity``'s reports summarised.

A training variant tried over seeds (docs/koopman.md) gives one ``model_fidelity.json``
per seed (``python -m studies.model_fidelity --artifact A --out DIR``). This reads them,
grouped, and prints per group the mean +- the standard deviation over the seeds of the
learned model's 1 s and 2 s open-loop RMSE of vy and yaw rate (on each seed's test runs),
as a ratio of a Table I row's mean where ``--reference`` names one, and how many seeds meet
the step-steer goals: the yaw rate within 5 % of the plant's at every speed, and issue 40's
vy goal (``studies.step_steer_spread.vy_within_goal``). It writes nothing:

    python -m studies.fidelity_summary --group 'w = 10=build/vy_matched/fidelity_w10_s*' \\
        --reference 'EDMDc physics dictionary, bilinear (edmdc-bilinear)'
"""
from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from studies.step_steer_spread import vy_within_goal

#: The step-steer yaw-rate goal (%, every speed).
YAW_TOLERANCE_PCT = 5.0
MEASURES = (("1 s", "vy"), ("1 s", "yaw_rate"), ("2 s", "vy"), ("2 s", "yaw_rate"))


def seed_figures(report: dict) -> dict[str, object]:
    """One seed's figures from its ``model_fidelity.json`` (the learned model's rows)."""
    learned = lambda row: str(row["model"]).startswith("learned")  # noqa: E731
    rmse = {(r["horizon"], state): float(value) for r in report["prediction"] if learned(r)
            for state, value in r["rmse"].items()}
    plant = {r["speed"]: r for r in report["step_steer"] if r["model"] == "plant"}
    model = {r["speed"]: r for r in report["step_steer"] if learned(r)}
    speeds = sorted(plant)
    return {"rmse": rmse, "yaw_errors": [float(model[v]["yaw_error_pct"]) for v in speeds],
            "vy_errors": [float(model[v]["vy"] - plant[v]["vy"]) for v in speeds],
            "plant_vy": [float(plant[v]["vy"]) for v in speeds], "speeds": speeds}


def reference_rmse(table1: Path, label: str) -> dict[tuple[str, str], float]:
    """The mean over seeds of a Table I row's 1 s and 2 s RMSE (``results/table1.json``)."""
    rows = {row["label"]: row for row in json.loads(table1.read_text())["rows"]}
    if label not in rows:
        raise SystemExit(f"error: --reference {label!r} is not a row of {table1}; rows: {sorted(rows)}")
    return {(h, s): float(np.mean([seed[s][h] for seed in rows[label]["seeds"]])) for h, s in MEASURES}


def markdown(groups: dict[str, list[dict]], reference: dict[tuple[str, str], float] | None) -> str:
    """The groups as a table, one column per group."""
    names = list(groups)
    lines = ["| measure | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for horizon, state in MEASURES:
        cells = []
        for name in names:
            values = np.array([seed["rmse"][(horizon, state)] for seed in groups[name]])
            cell = f"{values.mean():.4f} ± {values.std(ddof=1) if len(values) > 1 else 0.0:.4f}"
            if reference:
                cell += f" ({values.mean() / reference[(horizon, state)]:.2f} x)"
            cells.append(cell)
        lines.append(f"| {horizon} RMSE {state} | " + " | ".join(cells) + " |")
    yaw = [sum(max(abs(e) for e in s["yaw_errors"]) <= YAW_TOLERANCE_PCT for s in groups[n]) for n in names]
    vy = [sum(vy_within_goal(s["vy_errors"], s["plant_vy"]) for s in groups[n]) for n in names]
    lines.append("| step-steer yaw rate within 5 % | " + " | ".join(
        f"{k} of {len(groups[n])}" for k, n in zip(yaw, names)) + " |")
    lines.append("| step-steer vy within issue 40's goal | " + " | ".join(
        f"{k} of {len(groups[n])}" for k, n in zip(vy, names)) + " |")
    out = "\n".join(lines) + "\n\nvy 1 s after the step minus the plant's (m/s), per seed, at " + \
        " / ".join(f"{v:g}" for v in groups[names[0]][0]["speeds"]) + " m/s:\n"
    for name in names:
        out += f"- {name}: " + "; ".join(" / ".join(f"{e:+.4f}" for e in s["vy_errors"]) for s in groups[name]) + "\n"
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.fidelity_summary", description=__doc__.splitlines()[0])
    parser.add_argument("--group", action="append", required=True, metavar="LABEL=GLOB",
                        help="a group's label and the glob of its seeds' model_fidelity output folders (repeatable)")
    parser.add_argument("--reference", default=None, metavar="ROW", help="a Table I row whose mean RMSE the ratios use")
    parser.add_argument("--table1", type=Path, default=Path("results/table1.json"))
    args = parser.parse_args(argv)
    groups: dict[str, list[dict]] = {}
    for spec in args.group:
        label, sep, pattern = spec.rpartition("=")
        folders = [f for f in sorted(glob.glob(pattern)) if Path(f).is_dir()]
        if not sep or not folders:
            parser.error(f"--group {spec!r}: give LABEL=GLOB matching model_fidelity output folders")
        if label in groups:
            parser.error(f"--group {label!r} given twice")
        reports = [Path(f) / "model_fidelity.json" for f in folders]
        missing = [str(r) for r in reports if not r.is_file()]
        if missing:
            parser.error(f"--group {label}: no model_fidelity.json in {missing}")
        groups[label] = [seed_figures(json.loads(r.read_text())) for r in reports]
    reference = reference_rmse(args.table1, args.reference) if args.reference else None
    print(markdown(groups, reference), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

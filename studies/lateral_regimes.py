"""The small-signal yaw gain the training data hold, by driving regime.

The default learned model's step-steer yaw rate is 5-13 % low at 10-15 m/s over every seed
and training variant tried (``make step-steer-spread``). This study asks whether the data
themselves say so. At each step-steer speed it fits, by one-step least squares (Table I's
``DMDc``) on the default artefact's training runs within +-``BAND`` m/s of that speed, a
local linear model of the lateral states and the wheel angle,

    [vy, r, delta]_(k+1) = A [vy, r, delta]_k + B [torque, steer]_k + c,

once per regime of the samples (``REGIMES``: all of them, steady speed, braking, traction,
and gentle driving well inside the friction circle). It then drives each fit with the
plant's step steer (``studies.model_fidelity``: 0.02 rad from straight driving, the plant's
own torque) and reports the antisymmetric response 1 s later (half the difference of the
+0.02 and -0.02 rad steps) against the plant's: the yaw rate as an error in %, the lateral
velocity in m/s. The default artefact's antisymmetric response stands beside them.

A fit is one draw from a few hundred to a few thousand samples of a few dozen runs: read
differences of a few % between rows as noise; the finding is the contrast between the
gentle samples and those that include cornering near the limit. Longitudinal acceleration ax is the central difference of vx over Ts; grip use is
|vx r| / (mu g) (lateral) or hypot(ax, vx r) / (mu g) (combined), mu from the data set's
manifest.

Writes ``results/lateral_regimes.{md,json,png}``. A few seconds.
CLI: ``python -m studies.lateral_regimes [--data data/wide] [--artifact models/artifacts/dk_d5.npz]``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from models.errors import ModelError
from models.koopman import DEFAULT_ARTIFACT, KoopmanModel, KoopmanError
from models.local_lateral_fit import (BAND, INPUTS, STATES, LocalLateralModel, SampleSignals,  # noqa: F401
                                      antisymmetric_final, band_segments, friction_of_runs, local_fit, signals)
from studies.model_fidelity import STEP_SPEEDS, model_states, plant_step_steer

#: Regime name -> which samples (a boolean mask of SampleSignals' length).
REGIMES: dict[str, Callable[[SampleSignals], np.ndarray]] = {
    "all samples": lambda s: np.ones(s.ax.shape, dtype=bool),
    "steady speed, ax within ±0.2 m/s²": lambda s: np.abs(s.ax) < 0.2,
    "lateral grip use < 0.3": lambda s: s.lateral_grip < 0.3,
    "steady speed, ax within ±0.2 m/s², lateral grip use < 0.3": lambda s: (np.abs(s.ax) < 0.2) & (s.lateral_grip < 0.3),
    "steady speed, ax within ±0.2 m/s², lateral grip use < 0.1": lambda s: (np.abs(s.ax) < 0.2) & (s.lateral_grip < 0.1),
    "braking, ax < -0.5 m/s², lateral grip use < 0.3": lambda s: (s.ax < -0.5) & (s.lateral_grip < 0.3),
    "traction, ax > 0.5 m/s², lateral grip use < 0.3": lambda s: (s.ax > 0.5) & (s.lateral_grip < 0.3),
    "gentle, combined grip use < 0.1": lambda s: s.combined_grip < 0.1,
}


def antisymmetric_response(model: Any, states: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """(final(+step) - final(-step)) / 2 of ``model`` on the plant's step (``states`` (n + 1, 4),
    ``commands`` (n, 2)) from the plant's first state: the linear part of its response,
    [vx, vy, r, ...] after the step."""
    return antisymmetric_final(model, states[0, :model_states(model)], commands)


def measure(data_dir: Path, artifact: Path) -> dict[str, Any]:
    """Fit every regime at every speed on ``artifact``'s training runs of ``data_dir``."""
    from models.koopman_train import load_trajectories

    model = KoopmanModel.load(artifact)
    train_names = set(model.metadata.get("split", {}).get("train", []))
    if not train_names:
        raise KoopmanError(f"{artifact}: its JSON names no training runs (split.train)")
    mu = friction_of_runs(data_dir)
    runs = [r for r in load_trajectories(data_dir, STATES, INPUTS) if r.name in train_names]
    if not runs:
        raise KoopmanError(f"{data_dir}: none of {artifact.name}'s training runs are in this data set")
    unknown = [run.name for run in runs if run.name not in mu]
    if unknown:
        raise KoopmanError(f"{data_dir}: its manifest.json states no mu for {len(unknown)} training runs "
                           f"(first {unknown[0]}); the regimes' grip use needs each run's mu")
    per_run = [signals(run, mu[run.name]) for run in runs]
    out: dict[str, Any] = {"data_dir": str(data_dir), "artifact": str(artifact), "band": BAND,
                           "n_runs": len(runs), "speeds": list(STEP_SPEEDS), "plant": [], "model": [], "regimes": []}
    plant = {speed: plant_step_steer(speed) for speed in STEP_SPEEDS}
    for speed, (states, commands) in plant.items():
        out["plant"].append({"yaw_rate": float(states[-1, 2]), "vy": float(states[-1, 1])})
        learned = antisymmetric_response(model, states, commands)
        out["model"].append({"yaw_error_pct": float(100.0 * (learned[2] / states[-1, 2] - 1.0)), "vy": float(learned[1])})
    for name, select in REGIMES.items():
        cells = []
        masks = [select(s) for s in per_run]
        for speed, (states, commands) in plant.items():
            fit, n = local_fit(runs, masks, speed)
            if fit is None:
                cells.append({"samples": n})
                continue
            fitted = antisymmetric_response(LocalLateralModel(fit), states, commands)
            cells.append({"samples": n, "yaw_error_pct": float(100.0 * (fitted[2] / states[-1, 2] - 1.0)),
                          "vy": float(fitted[1])})
        out["regimes"].append({"regime": name, "cells": cells})
    return out


def _cell(cell: dict[str, Any]) -> str:
    if "yaw_error_pct" not in cell:
        return f"too few samples ({cell['samples']})"
    return f"{cell['yaw_error_pct']:+.1f} % / {cell['vy']:+.3f} ({cell['samples']})"


def markdown(result: dict[str, Any]) -> str:
    """The study's tables as markdown."""
    speeds = result["speeds"]
    lines = ["# The small-signal yaw gain the data hold, by driving regime", "",
             "Generated by `make lateral-regimes` (`studies/lateral_regimes.py`). Local one-step least-squares "
             f"fits of [vy, r, wheel angle] on {result['n_runs']} training runs of `{Path(result['artifact']).name}` "
             f"in `{result['data_dir']}`, samples within ±{result['band']:g} m/s of each speed, driven by the "
             "plant's 0.02 rad step steer. Each cell: the antisymmetric yaw-rate error 1 s after the step "
             "against the plant's / the antisymmetric lateral velocity (m/s) / (samples). The fits are noisy: "
             "read the contrast between gentle samples and those near the limit, not a few % between rows.", "",
             "![lateral regimes](lateral_regimes.png)", "",
             "| | " + " | ".join(f"{v:g} m/s" for v in speeds) + " |",
             "|---|" + "---|" * len(speeds),
             "| plant: yaw rate (rad/s) / vy (m/s) | "
             + " | ".join(f"{p['yaw_rate']:.4f} / {p['vy']:+.3f}" for p in result["plant"]) + " |",
             f"| learned model `{Path(result['artifact']).name}` | "
             + " | ".join(f"{m['yaw_error_pct']:+.1f} % / {m['vy']:+.3f}" for m in result["model"]) + " |"]
    for entry in result["regimes"]:
        lines.append(f"| local fit, {entry['regime']} | " + " | ".join(_cell(c) for c in entry["cells"]) + " |")
    return "\n".join(lines) + "\n"


#: Regimes drawn in the figure beside the learned model (the table has them all).
PLOTTED = ("all samples", "steady speed, ax within ±0.2 m/s²",
           "steady speed, ax within ±0.2 m/s², lateral grip use < 0.3", "gentle, combined grip use < 0.1")


def plot(result: dict[str, Any], path: Path) -> None:
    """Left: antisymmetric yaw-rate error (%) per speed of the learned model and of the local
    fits of ``PLOTTED``; right: the antisymmetric lateral velocity (m/s), the plant's as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    speeds = np.array(result["speeds"])
    series = [(f"learned model ({Path(result['artifact']).name})", result["model"])]
    series += [(f"local fit, {e['regime']}", e["cells"]) for e in result["regimes"] if e["regime"] in PLOTTED]
    fig, (yaw_ax, vy_ax) = plt.subplots(1, 2, figsize=(11.0, 4.2))
    width = 3.5 / len(series)
    for i, (label, cells) in enumerate(series):
        x = speeds + (i - (len(series) - 1) / 2) * width
        yaw = [c.get("yaw_error_pct", np.nan) for c in cells]
        vy = [c.get("vy", np.nan) for c in cells]
        yaw_ax.bar(x, yaw, width=width * 0.9, label=label)
        vy_ax.bar(x, vy, width=width * 0.9, label=label)
    yaw_ax.axhspan(-5.0, 5.0, color="0.9", zorder=0)
    yaw_ax.axhline(0.0, color="k", linewidth=0.8)
    yaw_ax.set_ylabel("yaw-rate error 1 s after the step (%)")
    vy_ax.plot(speeds, [p["vy"] for p in result["plant"]], "k_", markersize=30, markeredgewidth=2, label="plant")
    vy_ax.axhline(0.0, color="k", linewidth=0.8)
    vy_ax.set_ylabel("lateral velocity 1 s after the step (m/s)")
    for ax in (yaw_ax, vy_ax):
        ax.set_xticks(speeds)
        ax.set_xlabel("speed (m/s)")
    yaw_ax.set_title("Antisymmetric step-steer response: yaw rate vs plant")
    vy_ax.set_title("... and lateral velocity")
    vy_ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.lateral_regimes", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/wide"))
    parser.add_argument("--artifact", type=Path, default=DEFAULT_ARTIFACT)
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    args = parser.parse_args(argv)
    try:
        if not (args.data / "READY").is_file():
            raise KoopmanError(f"{args.data}: no data set (READY missing); make train generates data/wide")
        result = measure(args.data, args.artifact)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "lateral_regimes.md").write_text(markdown(result))
        (args.out / "lateral_regimes.json").write_text(json.dumps(result, indent=1) + "\n")
        plot(result, args.out / "lateral_regimes.png")
    except (ModelError, OSError, ValueError, KeyError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out / 'lateral_regimes.md'}, .json and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

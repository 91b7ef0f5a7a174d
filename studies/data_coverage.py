"""What a training data set covers: ``make data-coverage`` -> results/data_coverage.{png,md}.

For each data set given (default: the default artefact's ``data/wide`` and Fig. 7's
``data/nominal``), the distribution of speed, lateral acceleration over the friction limit
(|vx r| / (mu g), the steady-state share of the tyres' grip in use; > 1 means beyond
steady-state grip), steering command over its limit, drive torque, and mu per run
(from the generator's manifest). A markdown table gives the ranges and the shares of
samples in bands, so the reader sees that the data reach what the controller meets:
3-35 m/s, steering to the limit and into saturation, mu 0.3-1.0, traction and braking.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from models.dataset import load_dataset
from models.vehicle_params import load_vehicle_params

COLUMNS = ("time", "vx", "vy", "yaw_rate", "torque", "steer")
GRAVITY = 9.81


def coverage(directory: Path) -> dict:
    """Samples of one data set: vx (n,), grip use (n,), steer / limit (n,), torque (n,), mu per run."""
    manifest = json.loads((directory / "manifest.json").read_text())
    mu_of = {e["file"]: e.get("mu", manifest["params"]["mu"]) for e in manifest["runs"] if e.get("file")}
    runs = load_dataset(directory, columns=COLUMNS)
    steer_limit = load_vehicle_params().steer_limit
    parts: dict[str, list[np.ndarray]] = {"vx": [], "grip": [], "steer": [], "torque": []}
    mus = []
    for run in runs:
        mu = float(mu_of.get(f"{run.name}.csv", manifest["params"]["mu"]))
        mus.append(mu)
        vx, r = run.columns["vx"], run.columns["yaw_rate"]
        parts["vx"].append(vx)
        parts["grip"].append(np.abs(vx * r) / (mu * GRAVITY))
        parts["steer"].append(run.columns["steer"] / steer_limit)
        parts["torque"].append(run.columns["torque"])
    out = {name: np.concatenate(values) for name, values in parts.items()}
    out["mu"] = np.array(mus)
    out["hours"] = sum(len(r) for r in runs) * 0.025 / 3600.0
    return out


def summary_rows(name: str, data: dict) -> list[str]:
    """Markdown rows: ranges and the shares of samples in the bands that matter."""
    vx, grip, steer, torque = data["vx"], data["grip"], data["steer"], data["torque"]
    return [f"| {name} | {data['hours']:.2f} | {vx.min():.1f}-{vx.max():.1f} | "
            f"{100 * np.mean(vx < 8):.0f} / {100 * np.mean(vx > 28):.0f} | "
            f"{100 * np.mean(grip > 0.6):.0f} / {100 * np.mean(grip > 0.9):.0f} | "
            f"{np.abs(steer).max():.2f} | {100 * np.mean(np.abs(steer) > 0.5):.1f} | "
            f"{data['mu'].min():.2f}-{data['mu'].max():.2f} | "
            f"{100 * np.mean(torque > 200):.0f} / {100 * np.mean(torque < -200):.0f} |"]


def plot(datasets: dict[str, dict], path: Path) -> None:
    """Four histograms (speed, grip use, steer / limit, torque) and mu per run, one colour per set."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 5, figsize=(17, 3.4))
    specs = (("vx", "speed vx (m/s)", np.linspace(0, 37, 38)),
             ("grip", "|vx r| / (mu g)", np.linspace(0, 1.4, 29)),
             ("steer", "steer command / limit", np.linspace(-1, 1, 41)),
             ("torque", "drive torque (N m)", np.linspace(-3300, 2100, 37)),
             ("mu", "mu per run", np.linspace(0.25, 1.05, 17)))
    for ax, (key, label, bins) in zip(axes, specs):
        for name, data in datasets.items():
            values = data[key]
            weights = np.full(values.size, 100.0 / values.size)
            ax.hist(values, bins=bins, weights=weights, histtype="step", linewidth=1.5, label=name)
        ax.set_xlabel(label)
        ax.set_ylabel("% of " + ("runs" if key == "mu" else "samples"))
    axes[0].legend(fontsize=8)
    fig.suptitle("Training data coverage")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.data_coverage", description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", type=Path, default=[Path("data/wide"), Path("data/nominal")],
                        help="data set directories (models.data generate output)")
    parser.add_argument("--out", type=Path, default=Path("results"))
    args = parser.parse_args(argv)
    missing = [str(d) for d in args.data if not (d / "manifest.json").is_file()]
    if missing:
        print(f"error: no data set (manifest.json) in {', '.join(missing)}; generate it with "
              "`python -m models.data generate --out DIR [--profile wide]`", file=sys.stderr)
        return 2
    datasets = {d.name: coverage(d) for d in args.data}
    args.out.mkdir(parents=True, exist_ok=True)
    plot(datasets, args.out / "data_coverage.png")
    lines = ["# Training data coverage", "", "Written by `make data-coverage` (studies/data_coverage.py); "
             "histograms in [data_coverage.png](data_coverage.png). Grip use = |vx r| / (mu g).", "",
             "| data set | hours | vx range (m/s) | % vx < 8 / > 28 m/s | % grip use > 0.6 / > 0.9 | "
             "max abs steer / limit | % abs steer > half limit | mu range | % traction / braking |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, data in datasets.items():
        lines += summary_rows(name, data)
    (args.out / "data_coverage.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out / 'data_coverage.png'} and {args.out / 'data_coverage.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

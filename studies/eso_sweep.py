"""ESO-DKMPC's observer settings in closed loop (``make eso-sweep``): why the shipped tuning.

Runs ESO-DKMPC on both double lane changes of the study (``studies.closed_loop``, no CAN) for
a grid of observer settings: the two error poles of eq. 24 (``eso_pole``,
``eso_second_pole``) and how ``w_hat`` is spread over the horizon (``disturbance_decay``:
1 holds it, as eq. 15 does). DKMPC (no observer) and the shipped tuning are run beside
them in the same process, so every row compares with the same reference.

Writes to ``--out`` (default ``results/``):

- ``eso_dkmpc_sweep.md``: e_Y max / RMSE per setting and scenario, with the ratio to
  DKMPC's RMSE; the shipped row is marked;
- ``eso_dkmpc_sweep.png``: each setting's e_Y RMSE divided by DKMPC's, per scenario;
- ``eso_dkmpc_sweep.json``: the same numbers.

Usage: ``python -m studies.eso_sweep [--out DIR] [--scenarios ...]``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from studies.closed_loop import ClosedLoopResult, run_closed_loop
from hil.errors import HilError
from hil.scenario import Scenario, load_scenario

SCENARIOS = ("dlc_high_mu", "dlc_low_mu")


@dataclass(frozen=True)
class ObserverSetting:
    """One point of the sweep: the ESO's two error poles and the horizon decay of w_hat."""

    pole: float
    second_pole: float
    decay: float

    @property
    def label(self) -> str:
        held = "held" if self.decay == 1.0 else f"decay {self.decay:g}"
        return f"poles {self.pole:g} / {self.second_pole:g}, {held}"


#: Equal poles as in a one-parameter design, a fast/slow split, and decaying w_hat.
DEFAULT_GRID: tuple[ObserverSetting, ...] = (
    ObserverSetting(0.98, 0.98, 1.0),
    ObserverSetting(0.9, 0.9, 1.0),
    ObserverSetting(0.5, 0.5, 1.0),
    ObserverSetting(0.0, 0.97, 1.0),
    ObserverSetting(0.3, 0.95, 1.0),
    ObserverSetting(0.3, 0.97, 1.0),
    ObserverSetting(0.3, 0.98, 1.0),
    ObserverSetting(0.3, 0.99, 1.0),
    ObserverSetting(0.5, 0.5, 0.7),
    ObserverSetting(0.5, 0.5, 0.85),
    ObserverSetting(0.5, 0.5, 0.95),
    ObserverSetting(0.8, 0.8, 0.85),
    ObserverSetting(0.3, 0.97, 0.85),
)


@dataclass(frozen=True)
class SweepRow:
    """Closed-loop e_Y figures (m) of one controller setting on every scenario."""

    name: str
    setting: ObserverSetting | None  # None: DKMPC
    shipped: bool
    completed: dict[str, bool]
    max_abs: dict[str, float]
    rmse: dict[str, float]
    heading_rmse: dict[str, float]  # rad

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "shipped": self.shipped,
                "setting": None if self.setting is None else dataclasses.asdict(self.setting),
                "completed": self.completed, "max_abs_m": self.max_abs, "rmse_m": self.rmse,
                "heading_rmse_rad": self.heading_rmse}


#: Runs one controller (built by the callable) through one scenario.
Runner = Callable[[Scenario, Any], ClosedLoopResult]


def _row(name: str, setting: ObserverSetting | None, shipped: bool, build: Callable[[], Any],
         scenarios: Sequence[Scenario], runner: Runner, progress: tqdm) -> SweepRow:
    completed, max_abs, rmse, heading = {}, {}, {}, {}
    for scenario in scenarios:
        progress.set_postfix_str(f"{name} on {scenario.name}")
        result = runner(scenario, build())
        lateral = result.tracking.lateral
        completed[scenario.name] = result.completed
        max_abs[scenario.name] = float(lateral.max_abs)
        rmse[scenario.name] = float(lateral.rmse)
        heading[scenario.name] = float(result.tracking.heading.rmse)
        progress.update(1)
    return SweepRow(name, setting, shipped, completed, max_abs, rmse, heading)


def run_sweep(scenarios: Sequence[Scenario], grid: Sequence[ObserverSetting] = DEFAULT_GRID,
              *, runner: Runner = run_closed_loop, show_progress: bool = True) -> list[SweepRow]:
    """DKMPC, the shipped ESO-DKMPC and ESO-DKMPC at every ``grid`` setting on ``scenarios``.

    The shipped tuning is one more row (marked ``shipped``) unless it is on the grid, in
    which case that grid row is marked instead.
    """
    from controller.dkmpc import Dkmpc
    from controller.eso_dkmpc import EsoDkmpc
    from controller.tuning import load_tuning
    from models.koopman import KoopmanModel

    tuning = load_tuning()
    model = KoopmanModel.load()
    table = tuning.eso_dkmpc
    shipped = ObserverSetting(table.eso_pole, table.eso_second_pole, table.disturbance_decay)
    settings = list(grid) if shipped in grid else [shipped, *grid]

    def eso(setting: ObserverSetting) -> Callable[[], EsoDkmpc]:
        changed = dataclasses.replace(table, eso_pole=setting.pole, eso_second_pole=setting.second_pole,
                                      disturbance_decay=setting.decay)
        return lambda: EsoDkmpc(model, changed, tuning.longitudinal)

    rows = []
    with tqdm(total=(len(settings) + 1) * len(scenarios), desc="eso sweep", unit="run",
              disable=not show_progress) as progress:
        rows.append(_row("DKMPC", None, False, lambda: Dkmpc(model, tuning.dkmpc, tuning.longitudinal),
                         scenarios, runner, progress))
        for setting in settings:
            rows.append(_row("ESO-DKMPC", setting, setting == shipped, eso(setting), scenarios, runner,
                             progress))
    return rows


def sweep_table(rows: Sequence[SweepRow], scenario_names: Sequence[str]) -> str:
    """Markdown table: e_Y max / RMSE and heading RMSE per scenario, e_Y RMSE relative to DKMPC's."""
    reference = next(r for r in rows if r.setting is None)
    header = ["controller", "ESO poles", "w_hat over horizon"]
    for name in scenario_names:
        header += [f"{name} e_Y max / RMSE (m)", f"{name} e_Y RMSE vs DKMPC", f"{name} heading RMSE (rad)"]
    header.append("e_Y RMSE below DKMPC's on all")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        if row.setting is None:
            cells = [row.name, "-", "-"]
        else:
            held = "held (eq. 15)" if row.setting.decay == 1.0 else f"decay {row.setting.decay:g}^i"
            cells = [row.name + (" **(shipped)**" if row.shipped else ""),
                     f"{row.setting.pole:g} / {row.setting.second_pole:g}", held]
        beats = row.setting is not None
        for name in scenario_names:
            ok = row.completed[name]
            ratio = row.rmse[name] / reference.rmse[name]
            cells += [f"{row.max_abs[name]:.3f} / {row.rmse[name]:.4f}" + ("" if ok else " (stopped)"),
                      f"{ratio:.2f}", f"{row.heading_rmse[name]:.4f}"]
            beats = beats and ok and row.rmse[name] < reference.rmse[name]
        cells.append("-" if row.setting is None else ("yes" if beats else "no"))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "e_Y over every 25 ms control step (closed loop, four-wheel plant, no CAN; "
              "`python -m studies.eso_sweep`). Poles: the two error poles of eq. 24 in every lifted "
              "direction (`models.eso.design_gains`). 'held': w_hat constant over the horizon as "
              "in eq. 15; 'decay d^i': prediction step i adds d^i w_hat."]
    return "\n".join(lines) + "\n"


def plot_sweep(rows: Sequence[SweepRow], scenario_names: Sequence[str], path: Path) -> None:
    """Horizontal bars: each setting's e_Y RMSE divided by DKMPC's, per scenario (log axis).

    Bars left of 1 beat DKMPC; the shipped setting's label is bold.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    reference = next(r for r in rows if r.setting is None)
    settings = [r for r in rows if r.setting is not None]
    height = 0.8 / len(scenario_names)
    positions = np.arange(len(settings))[::-1]
    fig, ax = plt.subplots(figsize=(8.0, 0.45 * len(settings) + 1.6))
    for k, name in enumerate(scenario_names):
        ratios = [r.rmse[name] / reference.rmse[name] for r in settings]
        ax.barh(positions + (k - (len(scenario_names) - 1) / 2) * height, ratios, height=height,
                label=f"{name} (DKMPC: {reference.rmse[name]:.4f} m)")
    ax.axvline(1.0, color="k", linewidth=1.2, label="DKMPC (no observer)")
    ax.set_xscale("log")
    ax.set_yticks(positions, [r.setting.label + (" (shipped)" if r.shipped else "") for r in settings],
                  fontsize=8)
    for tick, row in zip(ax.get_yticklabels(), settings):
        tick.set_fontweight("bold" if row.shipped else "normal")
    ax.set_xlabel("ESO-DKMPC e_Y RMSE / DKMPC's (log scale; < 1 is better)")
    ax.set_title("ESO-DKMPC observer settings in closed loop (double lane changes)")
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from controller.errors import ControllerError
    from models.errors import ModelError

    parser = argparse.ArgumentParser(prog="python -m studies.eso_sweep", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS),
                        help="scenario names or TOML files (default: both lane changes)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    args = parser.parse_args(argv)
    try:
        scenarios = [load_scenario(name) for name in args.scenarios]
        rows = run_sweep(scenarios, show_progress=not args.no_progress)
    except (HilError, ControllerError, ModelError, OSError) as e:
        # A bad scenario, tuning file or Koopman artefact: say which, no traceback.
        print(f"error: {e}", file=sys.stderr)
        return 1
    names = [s.name for s in scenarios]
    args.out.mkdir(parents=True, exist_ok=True)
    table = sweep_table(rows, names)
    (args.out / "eso_dkmpc_sweep.md").write_text("### ESO-DKMPC observer settings against DKMPC\n\n" + table)
    (args.out / "eso_dkmpc_sweep.json").write_text(
        json.dumps({"generated_by": "python -m studies.eso_sweep", "scenarios": names,
                    "rows": [r.as_dict() for r in rows]}, indent=2) + "\n")
    if len(names) >= 2:
        plot_sweep(rows, names, args.out / "eso_dkmpc_sweep.png")
    print(table)
    print(f"wrote {args.out}/eso_dkmpc_sweep.md, .json" + (", .png" if len(names) >= 2 else ""))
    return 0

if __name__ == "__main__":
    sys.exit(main())

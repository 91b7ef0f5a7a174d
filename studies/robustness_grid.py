"""Robustness grid on our plant (issue 14 item 7, ``make robustness``): every controller in
closed loop with the four-wheel plant (``studies.closed_loop``, no CAN) over a grid of
road friction, speed, load, steering lag and manoeuvre.

The grid (:func:`grid_cells`, 4 x 3 x 2 x 2 x 2 = 96 cells per controller):

- ``mu`` 0.3 / 0.5 / 0.85 / 1.0 (the plant's road friction);
- ``speed_kmh`` 30 / 50 / 70: constant target speed, the run starts at that speed;
- ``mass_offset_kg`` +0 / +300 kg on the plant's nominal mass (the yaw inertia, the axle
  positions and the tyres stay the nominal ones, as in the scenarios' ``mass_offset_kg``);
- ``lag_factor`` x1 / x3: the plant's steering actuator time constant
  ``steer_time_constant`` (``models/vehicle.toml``, 30 ms) multiplied; the actuator's rate
  limit ``steer_rate_limit`` stays, so the factor changes the lag alone;
- ``manoeuvre``: the double lane change (``hil/paths/dlc.csv``) and the slalom
  (``hil/paths/slalom.csv``, ``hil.path_files.SLALOM``: 6 cones 24 m apart, passed 1 m
  to the side).

Each run starts on the path at X = 0 and lasts (end of the course in X + ``SETTLE_M``) /
speed + ``MARGIN_S``: the course, a short straight to settle, and a margin
(:func:`run_duration_s`). A run that leaves the road (|e_Y| > ``LEAVE_ROAD_M`` = 2 m: the
runner stops it there) or that the runner stops for any other reason (non-finite or
diverged plant, an exception in ``controller.step``) counts as not completed; one whose
controller or plant cannot even be built is recorded with its ``error``. The grid goes on
either way.

The runs are Ray tasks on the campaigns' executors (``studies.campaign.executors``): a
local Ray with ``--workers`` CPUs (default 2, one BLAS thread each), or the cluster at
``--address``; ``--workers 1`` runs them in this process. Each run's result is cached as
JSON in ``--cache`` (default ``build/robustness/``) under a hash of the cell, the
controller, the run's settings, the plant's parameters and the digests of the tuning
file, the model artefacts, the path files and the source of the controller and the runner
(:func:`run_key`), so a re-run resumes where it stopped and recomputes exactly the runs
whose inputs changed. The controllers are built from a copy of the tuning file taken when
the grid starts (a tuning sweep may rewrite ``controller/tuning.toml`` meanwhile); if
another input (an artefact, a path, a source file) changes while the grid runs, the runs
of that call are dropped from the cache and the grid stops with an error.

Writes to ``--out`` (default ``results/``):

- ``robustness.md``: (a) per controller the cells completed, the mean / median e_Y RMSE
  over the cells that every controller completed and on how many of those it has the
  lowest e_Y RMSE; (b) e_Y RMSE by mu x speed per controller (mean over the other axes,
  those cells only); (c) the measured ranking; (d) completed runs by mu x speed;
- ``robustness.csv``: one row per run (:data:`CSV_FIELDS`);
- ``robustness.png``: heat maps of e_Y RMSE over mu x speed per controller, double lane
  change and slalom at nominal mass and lag.

Usage: ``python -m studies.robustness_grid [--controllers ...] [--manoeuvres ...]
[--workers N] [--address ADDR] [--out DIR] [--cache DIR] [--no-cache] [--quick] [--no-progress] [--debug]``.
``--quick`` runs :data:`QUICK_CONTROLLERS` on :data:`QUICK_CELLS` (2 x 2 runs) into
``build/robustness-smoke/`` unless ``--out`` says otherwise. Exit status: 0 when the grid
ran (whatever each run's outcome), 1 when it could not (bad inputs, unwritable output),
2 for bad arguments.
"""
from __future__ import annotations

import os

# One BLAS thread per process, before numpy is imported here or in a spawned worker: the
# matrices are tiny and the workers already use the cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

# This module is the command (main); its parts, one job each: studies.robustness_cells
# (the grid's cells, a cell's scenario and plant), studies.robustness_runs (the runs and
# their cache), studies.robustness_summary (the summary of the records) and
# studies.robustness_report (the report lines, robustness.md / .csv / .png). The names that
# tests and other code import from studies.robustness_grid stay importable here.
import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

from controller.registry import ALL_CONTROLLER_NAMES  # noqa: E402
from hil.errors import HilError, StudyError  # noqa: E402,F401
from studies.robustness_cells import (GRID_CONTROLLERS, HORIZON_ROOM_M, MANOEUVRES, QUICK_CELLS,  # noqa: E402,F401
                                      QUICK_CONTROLLERS, SETTLE_M, Cell, build_plant, cell_scenario,
                                      grid_cells, plant_params, run_duration_s)
from studies.robustness_report import (goal_line, number_text, observer_line, ranking_line,  # noqa: E402,F401
                                       write_outputs)
from studies.robustness_runs import (CSV_FIELDS, DEFAULT_CACHE, LEAVE_ROAD_M, ROOT, RunRecord,  # noqa: E402,F401
                                     input_digests, run_grid, run_key)
from studies.robustness_summary import summarise  # noqa: E402,F401

#: Default output folder of ``--quick``.
QUICK_OUT = ROOT / "build" / "robustness-smoke"


# ---------------------------------------------------------------------------- CLI

def main(argv: list[str] | None = None) -> int:
    """CLI entry point (see the module docstring); returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.robustness_grid", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--controllers", nargs="+", choices=ALL_CONTROLLER_NAMES, default=None,
                        help=f"controllers (default: {' '.join(GRID_CONTROLLERS)}; "
                             f"--quick: {' '.join(QUICK_CONTROLLERS)})")
    parser.add_argument("--manoeuvres", nargs="+", choices=tuple(MANOEUVRES), default=tuple(MANOEUVRES),
                        help="manoeuvres (default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help="the smoke subset: 2 controllers x 2 cells, into build/robustness-smoke/")
    parser.add_argument("--workers", type=int, default=2,
                        help="Ray workers (default: 2; 1 runs in this process); on a cluster the "
                             "most runs at once")
    parser.add_argument("--address", default=None,
                        help="Ray cluster to use: auto, HOST:PORT or ray://HOST:PORT "
                             "(default: a local Ray on 127.0.0.1)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: results/)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                        help="cache folder (default: build/robustness/)")
    parser.add_argument("--no-cache", action="store_true", help="recompute every run")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--debug", action="store_true", help="tracebacks on errors")
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    controllers = tuple(args.controllers or (QUICK_CONTROLLERS if args.quick else GRID_CONTROLLERS))
    out = args.out or (QUICK_OUT if args.quick else ROOT / "results")
    command = "make robustness-smoke" if args.quick else "make robustness"
    started = time.monotonic()
    try:
        cells = list(QUICK_CELLS) if args.quick else grid_cells(args.manoeuvres)
        records = run_grid(cells, controllers, cache_dir=args.cache, workers=args.workers,
                           address=args.address, use_cache=not args.no_cache, show_progress=not args.no_progress)
        summary = write_outputs(records, controllers, out, command=command, workers=args.workers)
    except (HilError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 1
    from studies.report import display_name

    for row in summary.rows:
        print(f"{display_name(row.controller):<10} completed {row.completed:3d} of {row.runs}  "
              f"mean / median e_Y RMSE over common cells {number_text(row.common_rmse_mean)} / "
              f"{number_text(row.common_rmse_median)} m  lowest on {row.lowest_count}")
    print(ranking_line(summary))
    goal = goal_line(records)
    if goal:
        print(goal)
    observer = observer_line(records)
    if observer:
        print(observer)
    print(f"wrote {out}/robustness.md, robustness.csv, robustness.png "
          f"({len(records)} runs, {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    # Run the imported module's main, not this __main__ copy, as the other studies do.
    from studies.robustness_grid import main as _main

    sys.exit(_main())

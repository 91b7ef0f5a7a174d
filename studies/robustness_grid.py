"""Robustness grid on our plant (issue 14 item 7, ``make robustness``): the report of every
controller in closed loop with the four-wheel plant (no CAN) over road friction, speed,
load, steering lag and manoeuvre.

The grid is a campaign grid file, ``studies/campaign/grids/robustness_closed_loop.toml``
(4 x 3 x 2 x 2 x 2 = 96 cells per controller, 576 runs), run by the campaign engine like
every other grid: ``python -m studies.campaign robustness_closed_loop --out
build/robustness`` (Ray, local or a cluster, or ``--serial``; one cached result per cell,
so an interrupted grid resumes and a repeated one reruns only the cells whose inputs
changed). Its ``closed_loop`` runner (``studies.campaign.closed_loop_cell``) runs each cell
with ``studies.closed_loop.run_closed_loop``; each run starts on the path at X = 0 at its
constant speed and lasts (end of the course + ``SETTLE_M``) / speed + ``MARGIN_S``. A run
that leaves the road (|e_Y| > 2 m: the runner stops it there) or that the runner stops for
any other reason counts as not completed; one whose controller or plant cannot even be
built is recorded with its ``error``.

This command reads the campaign's cached rows for this checkout's code and writes to
``--out``:

- ``robustness.md``: (a) per controller the cells completed, the mean / median e_Y RMSE
  over the cells that every controller completed and on how many of those it has the
  lowest e_Y RMSE; (b) e_Y RMSE by mu x speed per controller (mean over the other axes,
  those cells only); (c) the measured ranking; (d) completed runs by mu x speed;
- ``robustness.csv``: one row per run (``studies.robustness_records.CSV_FIELDS``);
- ``robustness.png``: heat maps of e_Y RMSE over mu x speed per controller, double lane
  change and slalom at nominal mass and lag.

Usage: ``python -m studies.robustness_grid [GRID] --campaign DIR --out DIR [--controllers ...]``.
Exit status: 0 when the report was written, 1 when it could not (no campaign there, cells
missing, unwritable output), 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from controller.registry import ALL_CONTROLLER_NAMES
from hil.errors import HilError
from studies.robustness_cells import GRID, GRID_CONTROLLERS
from studies.robustness_records import records_from_rows
from studies.robustness_report import goal_line, number_text, observer_line, ranking_line, write_outputs


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point (see the module docstring); returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.robustness_grid", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("grid", nargs="?", default=GRID,
                        help=f"the campaign grid (a file, or a shipped grid's name; default {GRID})")
    parser.add_argument("--campaign", type=Path, required=True,
                        help="the folder the campaign ran into (python -m studies.campaign GRID --out DIR)")
    parser.add_argument("--out", type=Path, required=True, help="folder for robustness.{md,csv,png}")
    parser.add_argument("--controllers", nargs="+", choices=ALL_CONTROLLER_NAMES, default=None,
                        help="the report's controllers (default: those of the grid, in the study's order)")
    args = parser.parse_args(argv)
    from studies.campaign.grid import load_grid
    from studies.campaign.runner import cached_rows

    started = time.monotonic()
    try:
        grid = load_grid(args.grid)
        in_grid = list(dict.fromkeys(cell.controller for cell in grid.cells))
        order = [name for name in GRID_CONTROLLERS if name in in_grid] + \
                [name for name in in_grid if name not in GRID_CONTROLLERS]
        controllers = tuple(args.controllers or order)
        missing = [name for name in controllers if name not in in_grid]
        if missing:
            raise HilError(f"--controllers {' '.join(missing)}: not in the grid {grid.name}")
        if not (args.campaign / "cache").is_dir():
            raise HilError(f"--campaign {args.campaign}: no campaign there (run `python -m studies.campaign "
                           f"{args.grid} --out {args.campaign}` first)")
        rows = cached_rows(grid, args.campaign)
        wanted = sum(1 for cell in grid.cells if cell.controller in controllers)
        records = records_from_rows(rows, controllers)
        if len(records) < wanted:
            raise HilError(f"--campaign {args.campaign}: {wanted - len(records)} of the {wanted} runs of "
                           f"{grid.name} are not computed for this code (run the campaign first)")
        command = "python -m studies.robustness_grid " + " ".join(
            shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        summary = write_outputs(records, controllers, args.out, command=command)
    except (HilError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    from studies.report import display_name

    for row in summary.rows:
        print(f"{display_name(row.controller):<10} completed {row.completed:3d} of {row.runs}  "
              f"mean / median e_Y RMSE over common cells {number_text(row.common_rmse_mean)} / "
              f"{number_text(row.common_rmse_median)} m  lowest on {row.lowest_count}")
    print(ranking_line(summary))
    for line in (goal_line(records), observer_line(records)):
        if line:
            print(line)
    print(f"wrote {args.out}/robustness.md, robustness.csv, robustness.png "
          f"({len(records)} runs, {time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

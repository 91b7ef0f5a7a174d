"""``python -m studies.campaign GRID.toml --out DIR [--address ADDR] [--workers N]
[--serial] [--no-progress] [--debug]``: run a campaign grid (see docs/campaign.md).

GRID is a file or the name of a shipped grid (``studies/campaign/grids/NAME.toml``). Exit
status: 0 when the campaign ran (whatever each cell's outcome, as long as one cell ran), 1
for bad input, when Ray cannot start or when every cell failed to run (end reason
``error``), 2 for bad arguments, 130 when interrupted (finished cells are kept).
"""
from __future__ import annotations

import os

# Before numpy loads: the driver (and --serial cells) use one BLAS thread.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    from studies.campaign.executors import add_executor_arguments

    parser = argparse.ArgumentParser(prog="python -m studies.campaign",
                                     description="Run a campaign grid of HIL runs on Ray.")
    parser.add_argument("grid", help="grid TOML file, or a shipped grid's name (smoke, robustness)")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder: cells.csv, summary.md, heatmap_*.png, cache/ (rows.json: "
                             "every row of a grid whose cells are not cached, fault_case)")
    add_executor_arguments(parser)
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                        help="tqdm progress bar: cells done, failed, time left (default on)")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.workers is not None and args.workers < 1:
        print(f"error: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    if args.serial and args.address:
        print("error: --serial and --address exclude each other", file=sys.stderr)
        return 2
    from hil.errors import HilError

    try:
        return _run(args, argv)
    except HilError as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 1


def _run(args: argparse.Namespace, argv: Sequence[str] | None) -> int:
    from studies.campaign.grid import load_grid
    from studies.campaign.report import (ROWS_JSON, CsvAppender, summary_markdown, write_cells_csv,
                                         write_heatmaps, write_rows_json)
    from studies.campaign.executors import open_executor
    from studies.campaign.runner import (CampaignError, cached_rows, cell_cacheable, cell_task,
                                         check_c_ecu_built, is_prediction, run_campaign)
    from studies.machine import machine_description

    grid = load_grid(args.grid)  # every error before any cell runs
    check_c_ecu_built(grid)      # C cells without `make firmware`'s build: one error, no cell run
    out = args.out
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CampaignError(f"cannot create {out}: {e.strerror}") from e
    if is_prediction(grid):
        return _run_prediction(args, grid)
    appender = CsvAppender(out / "cells.csv", cached_rows(grid, out))
    executor = open_executor(cell_task(grid), address=args.address, workers=args.workers, serial=args.serial)
    try:
        result = run_campaign(grid, out, executor, progress=args.progress, on_row=appender)
    finally:
        executor.close()
    command = "python -m studies.campaign " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    write_cells_csv(out / "cells.csv", result.rows)
    (out / "summary.md").write_text(summary_markdown(
        grid, result.rows, command=command, wall_s=result.wall_s, executor=result.executor,
        computed=result.computed, cached=result.cached, machine=machine_description(),
        interrupted=result.interrupted), encoding="utf-8")
    written = [out / "cells.csv", out / "summary.md", *write_heatmaps(grid, result.rows, out)]
    if not all(cell_cacheable(cell) for cell in grid.cells):  # rows the cache does not keep
        written.append(write_rows_json(out / ROWS_JSON, result.rows))
    for path in written:
        print(f"wrote {path}")
    print(f"{len(result.rows)}/{result.total} cells finished ({result.computed} computed, "
          f"{result.cached} cached), {result.failed} not completed, {result.wall_s:.0f} s")
    if result.interrupted:
        print("interrupted: the finished cells are kept; run the same command to resume",
              file=sys.stderr)
        return 130
    errors = [row for row in result.rows if row.get("end_reason") == "error"]
    if result.rows and len(errors) == len(result.rows):
        print(f"error: every cell failed to run (the first: {errors[0].get('error') or 'no message'})",
              file=sys.stderr)
        return 1
    return 0


def _run_prediction(args: argparse.Namespace, grid) -> int:
    """A ``prediction`` grid (Table I's model rows x seeds): its cells' rows into
    ``rows.json`` (their report is ``python -m studies.table1``, which runs the same cells)."""
    from studies.campaign.executors import open_executor
    from studies.campaign.report import ROWS_JSON, write_rows_json
    from studies.campaign.runner import cell_task, run_campaign

    executor = open_executor(cell_task(grid), address=args.address, workers=args.workers, serial=args.serial)
    try:
        result = run_campaign(grid, args.out, executor, progress=args.progress)
    finally:
        executor.close()
    print(f"wrote {write_rows_json(args.out / ROWS_JSON, result.rows)}")
    print(f"{len(result.rows)}/{result.total} cells finished ({result.computed} computed, "
          f"{result.cached} cached), {result.failed} failed, {result.wall_s:.0f} s")
    if result.interrupted:
        return 130
    if result.rows and result.failed == len(result.rows):
        print(f"error: every cell failed (the first: {result.rows[0].get('error') or 'no message'})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

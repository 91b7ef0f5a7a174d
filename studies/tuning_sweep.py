"""One tuning procedure for every controller, on the tuning set only (``make tune``).

The evaluation (Tables II / III: the double lane changes ``dlc_high_mu``, ``dlc_low_mu``)
never enters: every run here is one of the tuning set's scenarios (``studies.tuning_set``,
``hil/scenarios/tuning/``), in closed loop with the four-wheel plant and no CAN
(``studies.closed_loop``): cells of the campaign engine's grid
``studies/campaign/grids/tuning_sweep.toml``, each evaluated setting a value of its
``tuning`` axis, run by the engine's executors (Ray local or a cluster, or this process)
and kept in its cache (``--cache``, default ``build/tuning_sweep``: an interrupted sweep
run again takes the cells it finished).

This module is the command (:func:`main`). Its parts, one job each:

- ``studies.tuning_sweep_grids``: the swept fields, the grids and the settings;
- ``studies.tuning_sweep_executor``: an evaluation of a setting on the scenarios (the
  objective);
- ``studies.tuning_sweep_cells``: the settings of a stage as campaign cells, run by the
  campaign engine;
- ``studies.tuning_sweep_procedure``: the procedure (its stages and the choice, in its
  docstring);
- ``studies.tuning_file``: the edits of the tuning file;
- ``studies.tuning_sweep_report``: the report, the figure and the JSON document;
- ``studies.tuning_sweep_reuse``: ``--reuse`` and ``--merge``.

Writes to ``--out`` (default ``results/``): ``tuning_sweep.md`` (per controller the grid,
the chosen setting and its objective, the top 5), ``tuning_sweep.json`` (every evaluation)
and ``tuning_sweep.png``; and, unless ``--no-write``, the chosen values into
``controller/tuning.toml`` (targeted edits of the swept fields of each controller's table,
re-read right before writing; every other line is kept).

Usage: ``python -m studies.tuning_sweep [--controllers ...] [--scenarios ...] [--workers N]
[--address ADDR] [--out DIR] [--tuning FILE] [--cache DIR] [--no-write] [--no-progress]
[--reuse JSON [--merge]]``;
``--report-from JSON`` only rewrites the report and figure from a stored ``tuning_sweep.json``.
``--controllers stanley --reuse results/tuning_sweep.json --merge`` tunes one controller and
keeps every other controller of the stored sweep in the reports as stored (the tuning file
is written for the named controllers only).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from hil.errors import HilError, StudyError
from studies.tuning_set import TUNING_SET, tuning_scenarios
# The command's parts. Besides what main uses, the names that tests and other code import
# from studies.tuning_sweep stay importable here.
from studies.tuning_file import TUNING_COMMENT, update_tuning_text, write_tuning_file  # noqa: F401
from studies.tuning_sweep_executor import FAILURE_PENALTY_M, build_controller, reuse_key  # noqa: F401
from studies.tuning_sweep_grids import (EXTRA_OBSERVER_STARTS, OBSERVER_FIELDS, OBSERVER_GRID,  # noqa: F401
                                        OBSERVER_START, STANLEY_GRID, WEIGHT_FIELDS, WEIGHT_GRID,
                                        SweepGrid, has_low_speed_weights, setting_text, stage_one_grid,
                                        stage_one_settings, stage_two_settings, swept_fields,
                                        with_low_speed_weights, with_setting)
from studies.tuning_sweep_cells import DEFAULT_CACHE
from studies.tuning_sweep_procedure import run_sweep
from studies.tuning_sweep_report import (SweepRecord, sweep_document, sweep_from_document,  # noqa: F401
                                         sweep_markdown, write_reports)
from studies.tuning_sweep_reuse import (KOOPMAN_CONTROLLERS, artefact_description, carried_sweeps,  # noqa: F401
                                        merged_sweeps, reusable_evaluations)


# ---------------------------------------------------------------------------- CLI

def main(argv: list[str] | None = None) -> int:
    """CLI: the sweep, its reports and (unless ``--no-write``) the tuning file's values."""
    from controller.errors import ControllerError
    from controller.registry import CONTROLLERS
    from controller.tuning import DEFAULT_TUNING_PATH, load_tuning
    from models.errors import ModelError
    from models.dmdc_model import DMDC_ARTIFACT
    from models.koopman import DEFAULT_ARTIFACT

    parser = argparse.ArgumentParser(prog="python -m studies.tuning_sweep",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--controllers", nargs="+", default=None,
                        help="registry names (default: every controller the registry builds)")
    parser.add_argument("--scenarios", nargs="+", default=None,
                        help=f"tuning scenario names (default: all {len(TUNING_SET)})")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                        help="Ray workers (default: 2, or 1 on a one-core machine; 1 runs in this "
                             "process); on a cluster the most runs at once")
    parser.add_argument("--address", default=None,
                        help="Ray cluster to use: auto, HOST:PORT or ray://HOST:PORT "
                             "(default: a local Ray on 127.0.0.1)")
    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder (default results/)")
    parser.add_argument("--tuning", type=Path, default=DEFAULT_TUNING_PATH,
                        help="tuning file read and (unless --no-write) updated")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, metavar="DIR",
                        help="the campaign cache of the sweep's cells (default build/tuning_sweep; "
                             "a rerun with the same code and tuning file takes the cells it holds)")
    parser.add_argument("--no-write", action="store_true", help="do not write the tuning file")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    parser.add_argument("--reuse", type=Path, default=None, metavar="JSON",
                        help="take the evaluations of an earlier sweep's tuning_sweep.json instead of "
                             "running them again (same scenarios required; the controllers on a model file "
                             "that changed since, the Koopman artefact or the DMDc model, run again; the "
                             "runs are deterministic, so only settings not in it run)")
    parser.add_argument("--merge", action="store_true",
                        help="with --reuse: the reports also keep every controller of the --reuse sweep "
                             "that --controllers does not name, as stored there (not run, not written "
                             "into the tuning file); tunes a controller without touching the others' results")
    parser.add_argument("--report-from", type=Path, default=None, metavar="JSON",
                        help="no sweep: rewrite the .md and .png in --out from a tuning_sweep.json "
                             "(the tuning file is not touched)")
    args = parser.parse_args(argv)
    if args.report_from is not None:
        try:
            record = sweep_from_document(json.loads(args.report_from.read_text()))
            write_reports(record, args.out, document=False)
        except (StudyError, OSError, json.JSONDecodeError) as e:
            print(f"error: {args.report_from}: {e}", file=sys.stderr)
            return 1
        print(f"wrote {args.out}/tuning_sweep.md, .png from {args.report_from}")
        return 0
    if args.merge and args.reuse is None:
        print("error: --merge keeps the controllers of the --reuse sweep: give --reuse JSON", file=sys.stderr)
        return 1
    controllers = list(args.controllers or CONTROLLERS)
    model_files = {"Koopman artefact used": Path(DEFAULT_ARTIFACT), "DMDc artefact used": DMDC_ARTIFACT}
    artefacts_before = {key: artefact_description(path) for key, path in model_files.items()}
    started = time.perf_counter()
    tally: dict[str, int] = {}
    try:
        scenarios = tuning_scenarios(args.scenarios)
        tuning = load_tuning(args.tuning)
        reuse = (None if args.reuse is None
                 else reusable_evaluations(args.reuse, [s.name for s in scenarios], artefacts_before))
        carried = (carried_sweeps(args.reuse, [s.name for s in scenarios], controllers, artefacts_before)
                   if args.merge else [])
        sweeps = run_sweep(controllers, scenarios, tuning, workers=args.workers, address=args.address,
                           show_progress=not args.no_progress, evaluate_before=True,
                           extra_observer_starts=EXTRA_OBSERVER_STARTS, reuse=reuse,
                           tuning_file=args.tuning, cache=args.cache, tally=tally)
    except (HilError, ControllerError, ModelError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    elapsed = time.perf_counter() - started
    for key, path in model_files.items():
        if artefact_description(path) != artefacts_before[key]:
            # Runs built before and after the change used different models: not one sweep.
            print(f"error: {path} changed during the sweep ({artefacts_before[key]} -> "
                  f"{artefact_description(path)}); run make tune again", file=sys.stderr)
            return 1
    stored = {(name, reuse_key(setting)) for name, setting in (reuse or {})}
    evaluated = [(s.controller, e) for s in sweeps for e in (*s.evaluations, *filter(None, (s.before,)))]
    reused = sum((name, reuse_key(e.setting)) in stored for name, e in evaluated)
    cached = tally.get("cached", 0)
    run_now = (len(evaluated) - reused) * len(scenarios) - cached
    context = {
        **artefacts_before,
        **({"Reused": f"{reused} evaluations ({reused * len(scenarios)} runs) from {args.reuse} "
                      "(--reuse: the same runs, not run again)"} if reuse else {}),
        **({"Carried over": f"{', '.join(s.controller for s in carried)} as stored in {args.reuse} "
                            f"(--merge: this sweep ran {', '.join(controllers)} only)"} if carried else {}),
        "Wall-clock time": f"{elapsed / 60:.1f} min with {args.workers} worker(s), {run_now} closed-loop runs"
                           + (f" ({cached} more from the campaign cache {args.cache})" if cached else ""),
    }
    write_reports(SweepRecord(merged_sweeps(carried, sweeps), [s.name for s in scenarios], context,
                              WEIGHT_GRID, OBSERVER_GRID, OBSERVER_START), args.out)
    for sweep in sweeps:
        print(f"{sweep.controller}: {setting_text(sweep.chosen.setting)} -> "
              f"{sweep.chosen.objective_m:.4f} m")
    print(f"wrote {args.out}/tuning_sweep.md, .json, .png in {elapsed / 60:.1f} min")
    if not args.no_write:
        chosen = {sweep.controller: with_low_speed_weights(sweep.chosen.setting) for sweep in sweeps}
        try:
            write_tuning_file(args.tuning, chosen)
            load_tuning(args.tuning)
        except (StudyError, ControllerError, OSError) as e:
            print(f"error: writing {args.tuning}: {e}", file=sys.stderr)
            return 1
        print(f"wrote the chosen values into {args.tuning}")
    return 0


if __name__ == "__main__":
    # Run the imported module's main, not this __main__ copy, as every study does (Ray
    # workers import the task function by name, from studies.campaign.cell).
    from studies.tuning_sweep import main as _main

    sys.exit(_main())

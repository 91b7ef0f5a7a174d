"""``eso-hil decode LOG --csv OUT.csv --plot OUT.png``: decoded signals of a CAN log.

The CSV has one row per frame (see `hil.decode_log`); the plot shows speed, steering
(command and measured), yaw rate, the path driven against the reference and e_Y.
``--dbc FILE`` decodes the log with another DBC (a foreign log: its own DBC), giving one
column per signal and one plot panel per message. Without ``--csv`` / ``--plot`` it
prints what the log holds. A log with nothing to plot gets a warning, not an empty
figure. Output files are checked before anything is read: an existing file needs
``--replace``, a missing folder is an error.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hil.commands import add_dbc_option, display_database, warn

HELP = "decode a recorded CAN log to a CSV table (one row per frame) and an overview plot"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``eso-hil decode``."""
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".db, .trc; optionally .gz; .mf4)")
    parser.add_argument("--csv", type=Path, default=None, metavar="OUT.csv",
                        help="write the decoded frames, one row per frame")
    parser.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                        help="write the overview plot")
    parser.add_argument("--path", action="append", default=[], metavar="ID=FILE",
                        help="reference path of a PATH_ID (repeatable); the plot uses the "
                        "PATH_ID the planner requested; default hil/paths/dlc.csv")
    add_dbc_option(parser, "decode the log with")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite existing --csv / --plot files")
    parser.add_argument("--json", action="store_true",
                        help="print what the log holds as JSON, alone on stdout (the 'wrote' "
                        "lines go to stderr)")


def main(args: argparse.Namespace) -> int:
    """Decode; write the requested files; 0 on success."""
    from firmware_sim.path_arguments import parse_paths
    from hil.decode_log import decode_log, decode_with_dbc, nothing_to_plot, write_csv
    from hil.logio import read_log
    from hil.output_paths import check_output_file

    paths = parse_paths(args.path)

    inputs = [args.log] + ([args.dbc] if args.dbc is not None else [])
    for option, target in (("--csv", args.csv), ("--plot", args.plot)):
        if target is not None:
            check_output_file(target, option, replace=args.replace, inputs=inputs)
    if args.csv is not None and args.plot is not None and args.csv.resolve() == args.plot.resolve():
        from hil.errors import OutputPathError

        raise OutputPathError(f"--csv and --plot are the same file {args.csv}")
    database, dbc_name = display_database(args.dbc)
    contents = read_log(args.log)
    for warning in contents.warnings:
        warn(f"{args.log}: {warning}")
    decoded = decode_log(contents) if database is None else decode_with_dbc(contents, database)
    report = sys.stderr if args.json else sys.stdout  # --json: stdout holds the JSON alone
    if not args.json:
        for line in contents.summary_lines(database, dbc_name):
            print(line)
        print(f"  time base: {decoded.time_base}")
        if decoded.e2e_counts:
            print("  E2E verdicts: " + ", ".join(f"{k} {v}"
                                                 for k, v in sorted(decoded.e2e_counts.items())))
        if decoded.undecodable:
            print(f"  frames that did not decode: {decoded.undecodable}")
    written: list[str] = []
    if args.csv is not None:
        write_csv(decoded, args.csv)
        written.append(str(args.csv))
        print(f"wrote {args.csv} ({len(decoded.rows)} rows)", file=report)
    if args.plot is not None:
        problem = nothing_to_plot(decoded)
        if problem is not None:
            warn(f"{args.log}: nothing to plot, {args.plot} not written: {problem}")
        else:
            _plot(args, decoded, database, dbc_name, paths)
            written.append(str(args.plot))
            print(f"wrote {args.plot}", file=report)
    if args.json:
        print(json.dumps(_summary(contents, decoded, database, dbc_name, written), indent=2))
    return 0


def _summary(contents: Any, decoded: Any, database: Any, dbc_name: str,
             written: list[str]) -> dict[str, Any]:
    """What ``--json`` prints: the counts of the text summary, as numbers."""
    from can_defs.frames import FrameId

    if database is None:
        per_message = {FrameId(fid).name: n for fid, n in sorted(contents.frames_by_id.items())}
        outside = dict(contents.unknown_ids)
    else:
        counted, outside = contents.counts_by_dbc(database)
        per_message = dict(counted.most_common())
    return {
        "log": str(contents.path), "dbc": dbc_name or "can_defs/vehicle.dbc",
        "frames": len(contents.messages), "complete": contents.complete,
        "frames_per_message": per_message,
        "ids_outside_dbc": {f"0x{fid:03X}": n for fid, n in sorted(outside.items())},
        "error_frames": contents.error_frames, "remote_frames": contents.remote_frames,
        "extended_frames": contents.extended_frames, "skipped_lines": contents.skipped_lines,
        "time_base": decoded.time_base, "e2e_verdicts": dict(sorted(decoded.e2e_counts.items())),
        "undecodable": decoded.undecodable, "warnings": list(contents.warnings),
        "wrote": written,
    }


def _plot(args: argparse.Namespace, decoded: object, database: object, dbc_name: str,
          paths: dict[int, Path]) -> None:
    from controller.reference import ReferencePath
    from hil.decode_log import most_requested_path_id, plot_log, plot_signals
    from hil.logio import REPO_ROOT, read_sidecar

    if database is not None:
        plot_signals(decoded, args.plot,  # type: ignore[arg-type]
                     title=f"{args.log.name}: signals decoded with {dbc_name}")
        return
    if not paths:
        metadata = read_sidecar(args.log)
        paths = ({k: Path(v) for k, v in metadata.paths.items()} if metadata and metadata.paths
                 else {})
    path_id = most_requested_path_id(decoded)  # type: ignore[arg-type]
    file = paths.get(path_id) if path_id is not None else None
    if file is None:
        file = next(iter(paths.values()), REPO_ROOT / "hil" / "paths" / "dlc.csv")
    reference = ReferencePath.from_csv(file)
    plot_log(decoded, reference, args.plot,  # type: ignore[arg-type]
             title=f"CAN log {args.log.name}: vehicle signals and tracking "
                   f"(reference path {Path(file).name})")

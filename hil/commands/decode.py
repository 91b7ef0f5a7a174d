"""``python -m hil decode LOG --csv OUT.csv --plot OUT.png``: decoded signals of a CAN log.

The CSV has one row per frame (see `hil.decode_log`); the plot shows speed, steering
(command and measured), yaw rate, the path driven against the reference and e_Y.
Without ``--csv`` / ``--plot`` it prints what the log holds.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "decode a recorded CAN log to a CSV table (one row per frame) and an overview plot"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m hil decode``."""
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".trc; optionally .gz)")
    parser.add_argument("--csv", type=Path, default=None, metavar="OUT.csv",
                        help="write the decoded frames, one row per frame")
    parser.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                        help="write the overview plot")
    parser.add_argument("--path", action="append", default=[], metavar="ID=FILE",
                        help="reference path of a PATH_ID (repeatable); the plot uses the "
                        "PATH_ID the planner requested; default hil/paths/dlc.csv")


def main(args: argparse.Namespace) -> int:
    """Decode; write the requested files; 0 on success."""
    from controller.reference import ReferencePath
    from firmware_sim.cli import parse_paths
    from hil.decode_log import decode_log, most_requested_path_id, plot_log, write_csv
    from hil.logio import REPO_ROOT, read_log, read_sidecar

    contents = read_log(args.log)
    for line in contents.summary_lines():
        print(line)
    for warning in contents.warnings:
        print(f"warning: {args.log}: {warning}", file=sys.stderr)
    decoded = decode_log(contents)
    print(f"  time base: {decoded.time_base}")
    print("  E2E verdicts: " + ", ".join(f"{k} {v}" for k, v in sorted(decoded.e2e_counts.items())))
    if args.csv is not None:
        write_csv(decoded, args.csv)
        print(f"wrote {args.csv} ({len(decoded.rows)} rows)")
    if args.plot is not None:
        paths = parse_paths(args.path)
        if not paths:
            metadata = read_sidecar(args.log)
            paths = ({k: Path(v) for k, v in metadata.paths.items()} if metadata and metadata.paths
                     else {})
        path_id = most_requested_path_id(decoded)
        file = paths.get(path_id) if path_id is not None else None
        if file is None:
            file = next(iter(paths.values()), REPO_ROOT / "hil" / "paths" / "dlc.csv")
        reference = ReferencePath.from_csv(file)
        plot_log(decoded, reference, args.plot, title=f"{args.log.name} (reference {Path(file).name})")
        print(f"wrote {args.plot}")
    return 0

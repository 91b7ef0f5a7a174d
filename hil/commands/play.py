"""``eso-hil play LOG --interface I --channel C``: put a recorded log on a CAN bus with
its original timing (python-can's `can.MessageSync`, as ``can.player``), optionally only
some IDs (``--ids``, by ID or by message name of ``--dbc``), faster or slower
(``--speed``), and with alive counters and CRCs rewritten (``--rewrite-e2e``) so that an
edited or spliced log drives another ECU. can.player's options keep their meaning:
``--ignore-timestamps``, ``--gap``, ``--skip`` (alias ``--max-gap``) and
``--error-frames`` (error frames are left out unless given).

A lockstep log is played as it was recorded, by time: its timestamps are the virtual
time of the drive, so it plays at the drive's true speed; nothing waits for HIL_SYNC_ACK
(use ``eso-hil replay`` for that). A progress bar shows on stderr for long logs
(off with ``--quiet`` or when stderr is not a terminal). The log and the options are
checked and the bus is opened before anything is printed: a bus that cannot be opened is
one ``error:`` line, exit 1.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from hil.commands import add_dbc_option, add_quiet_option, display_database, progress, warn

HELP = "play a recorded CAN log onto a bus with its original timing"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``eso-hil play``."""
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".db, .trc; optionally .gz; .mf4)")
    parser.add_argument("--interface", default=None,
                        help="python-can interface (default: python-can's configuration: "
                        "$CAN_INTERFACE, ~/.canrc; else virtual)")
    parser.add_argument("--channel", default=None,
                        help="CAN channel (default: python-can's configuration; else vcan0)")
    parser.add_argument("--ids", default=None, metavar="ID,...",
                        help="play only these IDs: 0x100,0x101 or message names of the DBC "
                        "(VEH_DYN,PLANNER_REQ)")
    add_dbc_option(parser, "name the messages of --ids and count the log's frames with")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="time factor: 2 plays twice as fast (default 1)")
    parser.add_argument("--rewrite-e2e", action="store_true",
                        help="re-number the contract's alive counters per ID and recompute CRCs")
    parser.add_argument("--skip", "--max-gap", dest="max_gap", type=float, default=None,
                        metavar="S", help="shorten pauses longer than S seconds (default 60)")
    parser.add_argument("--gap", type=float, default=None, metavar="S",
                        help="minimum time between two frames (default 0.0001, as can.player)")
    parser.add_argument("--ignore-timestamps", action="store_true",
                        help="send the frames back to back, --gap apart")
    parser.add_argument("--error-frames", action="store_true",
                        help="also send the log's error frames (left out by default)")
    add_quiet_option(parser)


def main(args: argparse.Namespace) -> int:
    """Play; print what was sent; 0 on success."""
    from hil.bus import open_bus, resolve_bus_config
    from hil.logio import read_log
    from hil.player import (DEFAULT_MAX_GAP_S, DEFAULT_MIN_GAP_S, PlayError, parse_ids, play,
                            rewrite_e2e, scale_timing, select_ids)

    if args.max_gap is not None and not args.max_gap > 0:
        raise PlayError(f"--skip/--max-gap must be > 0 s, got {args.max_gap}")
    if args.gap is not None and not args.gap >= 0:
        raise PlayError(f"--gap must be >= 0 s, got {args.gap}")
    if not args.speed > 0:
        raise PlayError(f"--speed must be > 0, got {args.speed}")
    database, dbc_name = display_database(args.dbc)
    names = None if database is None else {m.name: m.frame_id for m in database.messages}
    ids = parse_ids(args.ids, names) if args.ids is not None else None
    config = resolve_bus_config(args.interface, args.channel)
    contents = read_log(args.log)
    for warning in contents.warnings:
        warn(f"{args.log}: {warning}")
    messages = select_ids(contents.messages, ids)
    if not messages:
        raise PlayError(f"{args.log}: no frame left to play with --ids {args.ids}")
    stats = None
    if args.rewrite_e2e:
        messages, stats = rewrite_e2e(messages)
    messages = scale_timing(messages, args.speed)
    bus = open_bus(config)  # a bus that cannot be opened is the error, before any "playing"
    try:
        if stats is not None:
            print(f"rewrote E2E of {sum(stats.renumbered.values())} frames: "
                  f"{stats.counters_changed} counters changed, {stats.crcs_fixed} wrong CRCs fixed")
        duration = messages[-1].timestamp - messages[0].timestamp
        for line in contents.summary_lines(database, dbc_name)[1:]:
            print(line)
        errors = sum(m.is_error_frame for m in messages)
        left_out = f", {errors} error frames left out (--error-frames sends them)" \
            if errors and not args.error_frames else ""
        timing = "back to back" if args.ignore_timestamps else f"{duration:.3f} s"
        print(f"playing {len(messages) - (0 if args.error_frames else errors)} frames ({timing}) "
              f"on {config.describe()}{left_out}")
        sent = play(progress(messages, len(messages), "play", args.quiet), bus,
                    max_gap_s=DEFAULT_MAX_GAP_S if args.max_gap is None else args.max_gap,
                    min_gap_s=DEFAULT_MIN_GAP_S if args.gap is None else args.gap,
                    timestamps=not args.ignore_timestamps, error_frames=args.error_frames)
    finally:
        bus.shutdown()
    print(f"sent {sent} frames")
    return 0

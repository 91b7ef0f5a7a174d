"""``python -m hil play LOG --interface I --channel C``: put a recorded log on a CAN bus with
its original timing (python-can's `can.MessageSync`), optionally only some IDs
(``--ids``), faster or slower (``--speed``), and with alive counters and CRCs rewritten
(``--rewrite-e2e``) so that an edited or spliced log drives another ECU.

A lockstep log is played as it was recorded, by time: nothing waits for HIL_SYNC_ACK (use
``python -m hil replay`` for that).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "play a recorded CAN log onto a bus with its original timing"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m hil play``."""
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".trc; optionally .gz)")
    parser.add_argument("--interface", default=None,
                        help="python-can interface (default: $CAN_INTERFACE, else virtual)")
    parser.add_argument("--channel", default=None,
                        help="CAN channel (default: $CAN_CHANNEL, else vcan0)")
    parser.add_argument("--ids", default=None, metavar="ID,...",
                        help="play only these IDs: 0x100,0x101 or frame names (VEH_DYN,PLANNER_REQ)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="time factor: 2 plays twice as fast (default 1)")
    parser.add_argument("--rewrite-e2e", action="store_true",
                        help="re-number alive counters per ID and recompute CRCs")
    parser.add_argument("--max-gap", type=float, default=None, metavar="S",
                        help="shorten pauses longer than S seconds (default 60)")


def main(args: argparse.Namespace) -> int:
    """Play; print what was sent; 0 on success."""
    from hil.bus import open_bus, resolve_bus_config
    from hil.logio import read_log
    from hil.player import (DEFAULT_MAX_GAP_S, PlayError, parse_ids, play, rewrite_e2e,
                            scale_timing, select_ids)

    if args.max_gap is not None and not args.max_gap > 0:
        raise PlayError(f"--max-gap must be > 0 s, got {args.max_gap}")
    ids = parse_ids(args.ids) if args.ids is not None else None
    contents = read_log(args.log)
    for warning in contents.warnings:
        print(f"warning: {args.log}: {warning}", file=sys.stderr)
    messages = select_ids(contents.messages, ids)
    if not messages:
        raise PlayError(f"{args.log}: no frame left to play with --ids {args.ids}")
    if args.rewrite_e2e:
        messages, stats = rewrite_e2e(messages)
        print(f"rewrote E2E of {sum(stats.renumbered.values())} frames: "
              f"{stats.counters_changed} counters changed, {stats.crcs_fixed} wrong CRCs fixed")
    messages = scale_timing(messages, args.speed)
    duration = messages[-1].timestamp - messages[0].timestamp
    config = resolve_bus_config(args.interface, args.channel)
    print(f"playing {len(messages)} frames ({duration:.3f} s) on {config.describe()}")
    bus = open_bus(config)
    try:
        sent = play(messages, bus, max_gap_s=args.max_gap or DEFAULT_MAX_GAP_S)
    finally:
        bus.shutdown()
    print(f"sent {sent} frames")
    return 0

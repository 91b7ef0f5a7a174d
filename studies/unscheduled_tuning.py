"""The tuning file without the speed schedule of the weights (issue 35 item 6, the tables
with and without scheduling: ``make tables-unscheduled``).

Every MPC table of ``controller/tuning.toml`` has two weight sets (``MpcTuning.weights_at``):
``q_position``, ``q_yaw``, ``r_steer`` at and above 50 km/h and the ``low_speed_*`` twins at
and below 40 km/h, blended between. The sweep (``make tune``) chose the first set in its
steps 1-3 as one weighting for every speed and the low-speed set in its step 4. This writes
a copy of the tuning file whose low-speed twins equal the first set in every table: the
weights the same procedure chooses without a schedule. Everything else is copied as is.

Usage: ``python -m studies.unscheduled_tuning --out FILE [--tuning FILE] [--replace]``.
"""
from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path

from controller.tuning import DEFAULT_TUNING_PATH, SCHEDULED_WEIGHTS
from studies.tuning_file import update_tuning_text
from studies.tuning_sweep_grids import Setting

#: The comment each edited table carries.
COMMENT = "set equal to the weights above by studies.unscheduled_tuning: no speed schedule"


def unscheduled_text(text: str) -> str:
    """``text`` (a tuning file) with each table's ``low_speed_<w>`` set to its ``<w>`` for the
    scheduled weights ``w`` (tables without them are left alone)."""
    document = tomllib.loads(text)
    flat: dict[str, Setting] = {}
    for name, table in document.items():
        if isinstance(table, dict) and all(f"low_speed_{w}" in table and w in table for w in SCHEDULED_WEIGHTS):
            flat[name] = tuple((f"low_speed_{w}", float(table[w])) for w in SCHEDULED_WEIGHTS)
    return update_tuning_text(text, flat, comment=COMMENT)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.unscheduled_tuning", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tuning", type=Path, default=DEFAULT_TUNING_PATH, help="tuning file read")
    parser.add_argument("--out", type=Path, required=True, help="tuning file written")
    parser.add_argument("--replace", action="store_true", help="overwrite an existing --out")
    args = parser.parse_args(argv)
    if args.out.resolve() == args.tuning.resolve():
        print(f"error: --out {args.out} is the input tuning file", file=sys.stderr)
        return 1
    if args.out.exists() and not args.replace:
        print(f"error: --out {args.out} exists (--replace to overwrite)", file=sys.stderr)
        return 1
    if not args.out.parent.is_dir():
        print(f"error: --out {args.out}: no folder {args.out.parent}", file=sys.stderr)
        return 1
    try:
        text = args.tuning.read_text(encoding="utf-8")
        args.out.write_text(unscheduled_text(text), encoding="utf-8")
    except (OSError, tomllib.TOMLDecodeError) as e:
        print(f"error: {args.tuning}: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

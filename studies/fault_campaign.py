"""`make faults`: every fault of hil/faults.py in the high-mu double lane change, in
lockstep on the virtual bus, judged from the frames alone.

The cases (``hil.fault_cases.catalogue``) are the cells of the grid
``studies/campaign/grids/faults.toml`` (runner ``fault_case``), run through the campaign
engine on the campaigns' executors (``studies.fault_runs``), each judged from the frames
(``hil.fault_cases.verdicts``); the report goes to results/faults.*, rendered from the
cells' rows (``studies.fault_report``). The full 13.5 s scenario every
time (about 12-15 s of wall clock per run here); faults start at 3.0 s, in the first lane
change (X ~ 29 m).

``--ecu c`` (``make faults-c``) runs the same cases against the C ECU executable
(``build/firmware/ecu``) as ``hil run --ecu c`` does: a separate process on a socketcand hub
of its own on TCP loopback, the injector between this process's nodes and the hub
(``hil.fault_cases.c_ecu``; the grid ``faults_c.toml``). It writes results/faults_c.* and compares each verdict with the
Python campaign's (results/faults.json).

This module is the command: its options (shared with ``python -m hil faults --campaign``),
the executor they choose, and the run of the whole campaign (`run_from_args`).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hil.errors import HilError
from hil.fault_cases.catalogue import all_cases
from studies.fault_report import check_paths, write_results
from studies.fault_runs import run_campaign

#: The ECU implementations the campaign can drive (``hil.session.ECU_IMPLEMENTATIONS``).
ECUS = ("python", "c")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.fault_campaign [--out results] [--only NAME ...]``; exit 1 when a run
    crashed, sent an invalid command, left the path without a safe stop or missed a bound."""
    from can_defs.errors import CanDefsError

    parser = argparse.ArgumentParser(prog="python -m studies.fault_campaign", description=__doc__.split("\n")[0])
    add_arguments(parser)
    try:
        return run_from_args(parser.parse_args(argv))
    except (HilError, CanDefsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the campaign (``python -m hil faults --campaign`` has the same ones)."""
    from studies.campaign.executors import add_executor_arguments

    parser.add_argument("--out", type=Path, default=Path("results"), help="output folder")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite the results of an earlier campaign in --out")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME",
                        help="run only these cases (names as in the table)")
    parser.add_argument("--controllers", nargs="+", default=None,
                        help="restrict to these controllers")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="shorten the scenario (s); default the full 13.5 s")
    parser.add_argument("--ecu", choices=ECUS, default="python",
                        help="the Python ECU (results faults.*) or the C executable build/firmware/ecu "
                             "(results faults_c.*, compared with faults.*); default python")
    add_executor_arguments(parser, default_workers="none: without --workers or --address the runs "
                                                   "go to this process")


def executor_options(args: argparse.Namespace) -> dict[str, Any]:
    """Where the runs go: ``--serial`` or neither ``--workers`` nor ``--address``: this
    process; else Ray (local with ``--workers`` CPUs, or the cluster at ``--address``)."""
    address, workers = getattr(args, "address", None), getattr(args, "workers", None)
    if getattr(args, "serial", False) or (address is None and workers is None):
        if address is not None:
            raise HilError("--serial and --address exclude each other")
        return {"serial": True}
    return {"address": address, "workers": workers}


def run_from_args(args: argparse.Namespace) -> int:
    """Run the campaign as ``args`` say, write the results, print the summary."""
    cases = all_cases()
    if args.only:
        known = {c.name for c in cases}
        unknown = [n for n in args.only if n not in known]
        if unknown:
            raise HilError(f"unknown case(s) {unknown}; known: {sorted(known)}")
        cases = [c for c in cases if c.name in args.only]
    if args.duration is not None and not args.duration > 0:
        raise HilError(f"--duration must be > 0 s, got {args.duration}")
    ecu = getattr(args, "ecu", "python")   # `hil faults --campaign` has no --ecu
    if ecu == "c":
        from hil.session import check_c_ecu, default_options

        for controller in {c for case in cases for c in case.controllers}:
            if args.controllers is None or controller in args.controllers:
                check_c_ecu(default_options(controller, ecu="c"))
    check_paths(args.out, args.replace, ecu=ecu)
    started = time.monotonic()
    verdicts = run_campaign(cases, args.controllers, args.duration, executor_options(args), ecu)
    wall = time.monotonic() - started
    target = "make faults" + ("-c" if ecu == "c" else "")
    command = target if not (args.only or args.controllers or args.duration) \
        else ("python -m hil faults --campaign " if ecu == "python"
              else "python -m studies.fault_campaign ") + " ".join(
            f"--{k} {v if not isinstance(v, list) else ' '.join(map(str, v))}"
            for k, v in (("ecu", ecu if ecu != "python" else None), ("only", args.only),
                         ("controllers", args.controllers), ("duration", args.duration)) if v)
    for path in write_results(verdicts, args.out, wall, command, ecu):
        print(f"wrote {path}")
    ran = [v for v in verdicts if not v.not_applicable]
    bad = [v for v in ran if not v.passed()]
    print(f"{len(ran)} runs ({len(verdicts) - len(ran)} not applicable), "
          f"{sum(v.crashes for v in ran)} crashes, "
          f"{sum(v.invalid_commands for v in ran)} invalid commands, "
          f"{len(bad)} not meeting every criterion")
    return 1 if any(v.crashes or v.invalid_commands for v in ran) else 0


if __name__ == "__main__":
    sys.exit(main())

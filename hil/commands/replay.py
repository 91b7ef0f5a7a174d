"""``python -m hil replay LOG``: re-run the ECU on a recorded CAN log and compare its frames.

Exit status: 0 when the replayed STEER_TORQUE_CMD / CTRL_DIAG frames match the expected
ones (the log's own ECU frames, or ``--ref FILE``), 3 when they differ, 1 for bad input
(``error: ...``). With ``--write-ref`` the replay's frames are written as reference outputs
and the status is 0 once written (the comparison is then for information).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "re-run the ECU on a recorded CAN log and compare its output frames with the log's"

#: Exit status when the replayed frames differ from the expected ones.
EXIT_DIFFERENT = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m hil replay``."""
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".trc; optionally .gz)")
    parser.add_argument("--controller", default=None,
                        help="controller of the ECU (eso-dkmpc, dkmpc, lmpc, nmpc, or an ablation: "
                        "lmpc-eso, dmdc-eso); default: "
                        "the one in the log's sidecar <log>.json")
    parser.add_argument("--path", action="append", default=[], metavar="ID=FILE",
                        help="reference path of a PATH_ID (repeatable); default: the sidecar's, "
                        "else hil/paths/dlc.csv for every PATH_ID the log's planner requested")
    parser.add_argument("--realtime", action="store_true",
                        help="pace the frames by the log's timestamps (default: as fast as possible)")
    parser.add_argument("--ref", type=Path, default=None, metavar="FILE",
                        help="compare with these reference outputs instead of the log's ECU frames")
    parser.add_argument("--write-ref", nargs="?", const="", default=None, metavar="FILE",
                        help="write the replayed ECU frames as reference outputs (default file: "
                        "<log name>.ref.log next to the log)")
    parser.add_argument("--compare", choices=("exact", "tolerance"), default=None,
                        help="bit for bit (default for lockstep logs) or per signal with "
                        "tolerances (default for logs without HIL_SYNC)")
    parser.add_argument("--tol", action="append", default=[], metavar="SIGNAL=VALUE",
                        help="tolerance of one signal in --compare tolerance, e.g. "
                        "steer_angle_cmd=0.005 (repeatable)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE",
                        help="also write the report as JSON")
    parser.add_argument("--ack-timeout", type=float, default=None, metavar="S",
                        help="seconds to wait for each HIL_SYNC_ACK (default 10)")


def _tolerances(items: list[str]) -> dict[str, float]:
    from hil.replay import DEFAULT_TOLERANCES, ReplayError

    tolerances: dict[str, float] = {}
    for item in items:
        name, separator, value_text = item.partition("=")
        if not separator or name not in DEFAULT_TOLERANCES:
            raise ReplayError(f"--tol {item!r}: expected SIGNAL=VALUE with SIGNAL one of "
                              f"{', '.join(DEFAULT_TOLERANCES)}")
        try:
            value = float(value_text)
        except ValueError:
            raise ReplayError(f"--tol {item!r}: {value_text!r} is not a number") from None
        if not value >= 0:
            raise ReplayError(f"--tol {item!r}: a tolerance must be >= 0")
        tolerances[name] = value
    return tolerances


def controller_from_file_name(log: Path, names: tuple[str, ...]) -> str | None:
    """The controller of a log named as ``make run`` names them
    (``dlc_high_mu__eso-dkmpc.log``), None for any other name."""
    stem = log.name.split(".")[0]
    _, separator, controller = stem.rpartition("__")
    return controller if separator and controller in names else None


def main(args: argparse.Namespace) -> int:
    """Replay, print the report; see the module docstring for the exit status."""
    from controller.registry import ALL_CONTROLLER_NAMES
    from firmware_sim.cli import parse_paths
    from hil.logio import read_log, read_sidecar
    from hil.replay import (DEFAULT_ACK_TIMEOUT_S, ReplayError, default_paths_for,
                            reference_path_for, run_replay, write_reference)

    if args.ack_timeout is not None and not args.ack_timeout > 0:
        raise ReplayError(f"--ack-timeout must be > 0 s, got {args.ack_timeout}")
    tolerances = _tolerances(args.tol)
    contents = read_log(args.log)
    metadata = read_sidecar(args.log)
    if args.controller:
        controller, controller_source = args.controller, "--controller"
    elif metadata is not None:
        controller, controller_source = metadata.controller, "from the sidecar"
    elif (named := controller_from_file_name(args.log, ALL_CONTROLLER_NAMES)) is not None:
        controller, controller_source = named, "from the file name <scenario>__<controller>"
    else:
        raise ReplayError(
            f"{args.log}: the log does not say which controller ran (no sidecar "
            f"{args.log.name}.json); pass --controller NAME ({', '.join(ALL_CONTROLLER_NAMES)})")
    if controller not in ALL_CONTROLLER_NAMES:
        raise ReplayError(f"unknown controller {controller!r} ({controller_source}); choose one "
                          f"of {', '.join(ALL_CONTROLLER_NAMES)}")
    if args.path:
        paths, paths_source = parse_paths(args.path), "--path"
    elif metadata is not None and metadata.paths:
        paths = {k: Path(v) for k, v in metadata.paths.items()}
        paths_source = "from the sidecar"
    else:
        from hil.logio import REPO_ROOT

        paths = default_paths_for(contents, REPO_ROOT / "hil" / "paths" / "dlc.csv")
        paths_source = "default: hil/paths/dlc.csv for the PATH_IDs the log requested"
    for warning in contents.warnings:
        print(f"warning: {args.log}: {warning}", file=sys.stderr)

    writing = args.write_ref is not None
    report = run_replay(
        contents, controller, paths, controller_source=controller_source,
        paths_source=paths_source, reference=None if writing else args.ref,
        mode=args.compare, tolerances=tolerances, realtime=args.realtime,
        ack_timeout_s=args.ack_timeout or DEFAULT_ACK_TIMEOUT_S,
        allow_no_expected=writing)
    print(report.text())
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.as_dict(), indent=2) + "\n", encoding="utf-8")
    if writing:
        target = Path(args.write_ref) if args.write_ref else reference_path_for(args.log)
        if report.run.aborted:
            raise ReplayError(f"reference not written: {report.run.aborted}")
        write_reference(target, report.run.outputs)
        print(f"wrote {target} ({len(report.run.outputs)} frames)")
        return 0
    return 0 if report.match else EXIT_DIFFERENT

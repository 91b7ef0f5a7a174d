"""``eso-hil replay LOG``: re-run the ECU on a recorded CAN log and compare its frames.

Exit status, in every mode (exact or tolerance comparison, ``--ref``, ``--realtime``):

- 0 (:data:`EXIT_MATCH`): the replayed STEER_TORQUE_CMD / CTRL_DIAG frames match the
  expected ones (the log's own ECU frames, or ``--ref FILE``);
- 3 (:data:`EXIT_DIFFERENT`): they differ, or the ECU stopped answering (replay aborted);
- 1 (:data:`EXIT_ERROR`): bad input, one ``error: ...`` line: no such log, a log without
  the ECU's inputs (nothing to replay), nothing to compare with, unknown controller, an
  output file that exists without ``--replace``, a file the sidecar recorded (path,
  model, excitation program, the controller's default model, vehicle file or C ECU data
  file) that is missing or changed, a real-time recording (the sidecar's ``mode``)
  without ``--compare tolerance``, ``--ref`` or ``--write-ref``
  (`check_realtime_comparison`); 2: a bad option (argparse).

The ECU is rebuilt as the sidecar recorded it (controller, paths, ``--model``,
``--excite``); the options of the same names replace the sidecar's.

``--write-ref [FILE]`` writes the replay's frames as reference outputs: 0 once written
(the comparison with the log's own frames is then shown for information), 1 when
nothing was written (a log without inputs, an aborted replay).

``--json`` alone prints the report as JSON, alone on stdout (the text report goes to
stderr); ``--json FILE`` writes it to FILE besides the text report. ``--dbc FILE``
changes how the log's frames are counted and named in the report, never the DBC of the
ECU under replay (always the project's). Output files are checked before the replay
runs (an existing file needs ``--replace``; a missing folder is an error).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hil.commands import (add_dbc_option, add_ecu_input_options, add_quiet_option, controller_name,
                          display_database,
                          progress, warn)

HELP = "re-run the ECU on a recorded CAN log and compare its output frames with the log's"

#: Exit status when the replayed frames match the expected ones (or a reference was written).
EXIT_MATCH = 0
#: Exit status for bad input or a replay that could not run (``error: ...``).
EXIT_ERROR = 1
#: Exit status when the replayed frames differ from the expected ones.
EXIT_DIFFERENT = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``eso-hil replay``."""
    parser.epilog = ("exit status (every mode): 0 MATCH, 3 DIFFERENT (or the ECU stopped "
                     "answering), 1 error, 2 bad option; with --write-ref: 0 written, 1 not "
                     "written. Give --json after LOG (eso-hil replay LOG --json): before it, "
                     "--json takes LOG as its FILE.")
    parser.add_argument("log", type=Path, help="recorded log (.log candump, .asc, .blf, .csv, "
                        ".db, .trc; optionally .gz; .mf4)")
    parser.add_argument("--controller", default=None,
                        help="controller of the ECU (eso-dkmpc, dkmpc, lmpc, nmpc, an ablation: "
                        "lmpc-eso, dmdc-eso, or the geometric baseline stanley); default: "
                        "the one in the log's sidecar <log>.json")
    parser.add_argument("--path", action="append", default=[], metavar="ID=FILE",
                        help="reference path of a PATH_ID (repeatable); default: the sidecar's, "
                        "else hil/paths/dlc.csv for every PATH_ID the log's planner requested")
    add_ecu_input_options(parser, "; default: the sidecar's")
    parser.add_argument("--realtime", action="store_true",
                        help="pace the frames by the log's timestamps (default: as fast as possible)")
    parser.add_argument("--ref", type=Path, default=None, metavar="FILE",
                        help="compare with these reference outputs instead of the log's ECU frames")
    parser.add_argument("--write-ref", nargs="?", const="", default=None, metavar="FILE",
                        help="write the replayed ECU frames as reference outputs (default file: "
                        "<log name>.ref.log next to the log)")
    parser.add_argument("--compare", choices=("exact", "tolerance"), default=None,
                        help="bit for bit (default for lockstep logs) or per signal with "
                        "tolerances (default for logs without HIL_SYNC; to be given for a "
                        "real-time recording, which is refused without it, --ref or --write-ref)")
    parser.add_argument("--tol", action="append", default=[], metavar="SIGNAL=VALUE",
                        help="tolerance of one signal in --compare tolerance, e.g. "
                        "steer_angle_cmd=0.005 (repeatable)")
    parser.add_argument("--json", nargs="?", const="-", default=None, metavar="FILE",
                        help="the report as JSON: alone on stdout (text report on stderr), or "
                        "written to FILE")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite an existing --json / --write-ref file")
    add_dbc_option(parser, "count and name the log's frames with in the report")
    add_quiet_option(parser)
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
    from firmware_sim.path_arguments import parse_paths
    from hil.logio import read_log, read_sidecar
    from hil.output_paths import check_output_file
    from hil.replay import (DEFAULT_ACK_TIMEOUT_S, ReplayError, default_paths_for,
                            reference_path_for, run_replay, write_reference)

    if args.ack_timeout is not None and not args.ack_timeout > 0:
        raise ReplayError(f"--ack-timeout must be > 0 s, got {args.ack_timeout}")
    tolerances = _tolerances(args.tol)
    writing = args.write_ref is not None
    target = (Path(args.write_ref) if args.write_ref else reference_path_for(args.log)) \
        if writing else None
    json_file = Path(args.json) if args.json not in (None, "-") else None
    inputs = [args.log] + ([args.ref] if args.ref is not None else []) \
        + ([args.dbc] if args.dbc is not None else [])
    for option, output in (("--write-ref", target), ("--json", json_file)):
        if output is not None:
            check_output_file(output, option, replace=args.replace, inputs=inputs)
    paths_given = parse_paths(args.path) if args.path else None
    controller_given = controller_name(args.controller) if args.controller else None
    database, dbc_name = display_database(args.dbc)
    contents = read_log(args.log)
    metadata = read_sidecar(args.log)
    if metadata is not None and metadata.mode == "realtime":
        check_realtime_comparison(args, writing)
    if controller_given is not None:
        controller, controller_source = controller_given, "--controller"
    elif metadata is not None:
        controller, controller_source = metadata.controller, "from the sidecar"
    elif (named := controller_from_file_name(args.log, ALL_CONTROLLER_NAMES)) is not None:
        controller, controller_source = named, "from the file name <scenario>__<controller>"
    else:
        raise ReplayError(
            f"{args.log}: the log does not say which controller ran (no sidecar "
            f"{args.log.name}.json); pass --controller NAME ({', '.join(ALL_CONTROLLER_NAMES)})")
    controller = controller_name(controller, f"controller ({controller_source})")
    if paths_given is not None:
        paths, paths_source = paths_given, "--path"
    elif metadata is not None and metadata.paths:
        paths = {k: Path(v) for k, v in metadata.paths.items()}
        paths_source = "from the sidecar"
    else:
        from hil.logio import REPO_ROOT

        paths = default_paths_for(contents, REPO_ROOT / "hil" / "paths" / "dlc.csv")
        paths_source = "default: hil/paths/dlc.csv for the PATH_IDs the log requested"
    for warning in contents.warnings:
        warn(f"{args.log}: {warning}")
    controller_factory, excitation, setup, notes = _recorded_ecu(args, metadata, controller)

    report = run_replay(
        contents, controller, paths, controller_source=controller_source,
        paths_source=paths_source, reference=None if writing else args.ref,
        mode=args.compare, tolerances=tolerances, realtime=args.realtime,
        ack_timeout_s=args.ack_timeout or DEFAULT_ACK_TIMEOUT_S,
        allow_no_expected=writing, display_database=database, dbc_name=dbc_name,
        wrap_inputs=lambda frames: progress(frames, len(frames), "replay", args.quiet),
        controller_factory=controller_factory, excitation=excitation)
    report.setup.extend(setup)
    report.notes.extend(notes)
    as_json = json.dumps(report.as_dict(), indent=2)
    text_stream = sys.stderr if args.json == "-" else sys.stdout
    if writing:
        if report.run.aborted:
            print(report.text(), file=text_stream)
            raise ReplayError(f"reference not written: {report.run.aborted}")
        write_reference(target, report.run.outputs)  # type: ignore[arg-type]
    print(report.text(writing=writing), file=text_stream)
    if args.json == "-":
        print(as_json)
    elif json_file is not None:
        json_file.write_text(as_json + "\n", encoding="utf-8")
    if writing:
        print(f"wrote {target} ({len(report.run.outputs)} frames)", file=sys.stderr)
        return EXIT_MATCH
    return EXIT_MATCH if report.match else EXIT_DIFFERENT


def check_realtime_comparison(args: argparse.Namespace, writing: bool) -> None:
    """A real-time recording (the sidecar's ``mode``) is compared only in a way that can
    hold: per signal with tolerances (``--compare tolerance``, asked for), or with a
    reference a replay wrote (``--ref``; ``--write-ref`` writes one). Its recorded commands
    depend on the host's timing (when each control task ran, its overruns), which no log
    holds, so a replay cannot reproduce them: a plain replay would report DIFFERENT for the
    host's timing alone.

    Raises:
        ReplayError: none of these was given (one line, saying which to give).
    """
    from hil.logio import sidecar_path
    from hil.replay import ReplayError

    if writing or args.ref is not None or args.compare == "tolerance":
        return
    raise ReplayError(
        f"{args.log}: a real-time recording ('mode': 'realtime' in {sidecar_path(args.log)}): "
        "its ECU's commands depend on the host's timing (when each control task ran, its "
        "overruns), which no log holds, so a replay cannot reproduce them; compare per signal "
        "with --compare tolerance [--tol SIGNAL=VALUE] (differences beyond the tolerances are "
        "reported), or with a replay's own reference (--write-ref, then --ref FILE)")


def _recorded_ecu(args: argparse.Namespace, metadata: Any,
                  controller: str) -> tuple[Any, Any, list[str], list[str]]:
    """The ECU's ``--model`` and ``--excite`` (the options, else the sidecar's), checked
    against the hashes the sidecar recorded: the controller factory, the excitation
    program, the report's lines about them and its notes.

    Raises:
        ReplayError: a recorded input file the replay would read is missing or changed
            (one sentence per file; the options that replace each are named).
    """
    from firmware_sim.controller_factory import model_controller_factory
    from firmware_sim.excitation import load_excitation
    from hil.logio import check_input_files, sidecar_path
    from hil.replay import ReplayError

    recorded_model = None if metadata is None else metadata.model
    recorded_excite = None if metadata is None else metadata.excite
    model = args.model if args.model is not None else \
        (Path(recorded_model) if recorded_model is not None else None)
    excite = args.excite if args.excite is not None else recorded_excite
    setup = [f"{name}: {value} ({'--' + option if given else 'from the sidecar'})"
             for name, option, value, given in (
                 ("model", "model", model, args.model is not None),
                 ("excitation", "excite", excite, args.excite is not None)) if value is not None]
    notes: list[str] = []
    if metadata is not None:
        # the files the replay takes from elsewhere are not the sidecar's business
        given = {"model", "default model"} if args.model is not None else set()
        given |= {"excite"} if args.excite is not None else set()
        given |= {f.role for f in metadata.input_files if f.role.startswith("path ") and args.path}
        if controller != metadata.controller:  # another controller reads its own files
            given |= {"default model", "vehicle", "C ECU data"}
        problems = check_input_files(metadata.input_files, skip_roles=given)
        # The tuning is part of the build, like the code: a replay against a changed build
        # is what finds a regression, so it runs and says why it may differ.
        notes.extend(f"{sentence}: the replayed ECU is not the recorded build, a divergence "
                     "is expected" for recorded, sentence in problems if recorded.role == "tuning")
        refused = [(recorded, sentence) for recorded, sentence in problems
                   if recorded.role != "tuning"]
        if refused:
            options = sorted({option for f, _ in refused
                              if (option := _replacing_option(f.role, controller)) is not None})
            raise ReplayError(
                f"{args.log}: cannot rebuild the recorded ECU: "
                + "; ".join(sentence for _, sentence in refused)
                + f" (hashes in {sidecar_path(args.log)}); restore the file"
                + (f", or replay with another through {' / '.join(options)}" if options else ""))
        if metadata.ecu == "c":
            notes.append("the log was recorded with the C ECU (firmware/); the replay runs the "
                         "Python ECU (firmware_sim)")
    for note in notes:
        warn(f"{args.log}: {note}")
    factory = None if model is None else model_controller_factory(controller, model)
    return factory, load_excitation(excite), setup, notes


def _replacing_option(role: str, controller: str) -> str | None:
    """The replay option that gives another file for a recorded file of ``role``, None
    when there is none (the vehicle file, the C ECU's data file, the default model of a
    controller that takes no ``--model``)."""
    from controller.registry import MODEL_FILE_KINDS

    if role.startswith("path "):
        return "--path ID=FILE"
    if role in ("model", "excite"):
        return f"--{role}"
    if role == "default model" and controller in MODEL_FILE_KINDS:
        return "--model"
    return None

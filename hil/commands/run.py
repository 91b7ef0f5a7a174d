"""``eso-hil run``: one scenario with one controller over CAN.

On the ``virtual`` interface (the default) everything runs in this process; on any other
interface (``--interface socketcan --channel vcan0``) the ECU is a separate process
started through ``eso-ecu`` (``python -m firmware_sim``). ``--ecu c`` runs the C ECU
executable (``build/firmware/ecu``, ``make firmware``) as that process instead, on the
virtual interface through a socketcand hub of the run's own on loopback (hil/session.py);
``--model`` is then converted to its data file first. Prints the tracking metrics as
JSON, alone on stdout (``wrote`` lines and notes go to stderr); ``--out`` writes
the time series (``plant.csv``, ``ecu.csv``) and ``summary.json``; ``--log`` records every
frame (format by suffix: ``.log`` candump, ``.asc``, ``.blf``, ``.csv``, ``.db``, ``.trc``,
optionally ``.gz``, and ``.mf4``: the formats `hil.logio` reads back; any other suffix is
refused before the run). A lockstep log is stamped with virtual time (`hil.recorder`).

Every input and output is checked before anything runs or is written: the controller
name (any case), the scenario and
its path file (the contract's path checks), the DBC, and the outputs: ``--log`` and
``--out`` are never one of the run's inputs, their folders must exist, and an existing log
or an ``--out`` folder holding another run's outputs is an error unless ``--replace`` is
given. ``--model`` and ``--excite`` get the ECU's own checks first. A bad option value
(an unknown controller, a ``--scenario`` that names no file and no shipped scenario, a
timeout <= 0, a ``--model`` or ``--excite`` file the ECU cannot use, an unusable
``--log``, ``--out`` or ``--plot``) is one ``error:`` line and exit 2
(`hil.errors.OptionError`), as argparse's own option errors and ``eso-ecu``'s; a scenario
or path file that does not load, a bus that does not open and a failed run exit 1.
``--out`` is the one folder a run creates (its parent must exist). SIGTERM and SIGHUP end the run as SIGINT does (ECU stopped with its last
CMD_VALID = 0 frame, log flushed, sidecar written; exit 143 / 129 / 130).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

from hil.commands import add_ecu_input_options, controller_name

#: ``--plot`` given without a file: a window only.
SHOW_ONLY = Path("")

HELP = "run one scenario with one controller over CAN (plant, planner, time master, ECU)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``eso-hil run``."""
    parser.add_argument("--scenario", required=True,
                        help="scenario TOML file, or the name of a shipped one (dlc_high_mu)")
    parser.add_argument("--controller", required=True,
                        help="controller of the ECU: eso-dkmpc, dkmpc, lmpc or nmpc, an ablation "
                             "(lmpc-eso, dmdc-eso) or the geometric baseline stanley; any case")
    parser.add_argument("--interface", default=None,
                        help="python-can interface (default: $CAN_INTERFACE, else virtual)")
    parser.add_argument("--channel", default=None,
                        help="CAN channel (default: $CAN_CHANNEL, else vcan0)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", dest="lockstep", action="store_true", default=True,
                      help="virtual time driven by HIL_SYNC (default; deterministic)")
    mode.add_argument("--realtime", dest="lockstep", action="store_false",
                      help="every node on its own wall clock")
    parser.add_argument("--log", type=Path, default=None,
                        help="record every frame to this file (.log candump, .asc, .blf, .csv, "
                             ".db, .trc; optionally .gz; .mf4): the formats eso-hil reads back")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for plant.csv, ecu.csv and summary.json (created if missing; its "
                             "parent must exist)")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite an existing --log file (and its sidecar) and the outputs "
                             "of an earlier run in --out")
    parser.add_argument("--faults", action="store_true",
                        help="inject the scenario's [faults] table (bus, vehicle, sensor faults of "
                             "hil/faults.py; without it only its mu_step acts)")
    parser.add_argument("--plot", nargs="?", type=Path, const=SHOW_ONLY, default=None,
                        metavar="FILE.png",
                        help="a live view of the run (path and vehicle, e_Y, steering, mode and "
                             "task time) in a window when a display exists; with FILE, its last "
                             "frame is written there too (png, pdf, svg, ...). Without a display "
                             "only FILE is written (--plot alone: a note, the run goes on)")
    add_ecu_input_options(parser)
    parser.add_argument("--ecu", choices=("python", "c"), default="python", type=str.lower,
                        help="the ECU: python (firmware_sim, default) or c (the C executable "
                             "build/firmware/ecu of make firmware; eso-dkmpc, dkmpc, lmpc)")
    parser.add_argument("--handshake-timeout", type=float, default=None, metavar="S",
                        help="seconds to wait for the ECU's lockstep handshake (default 60)")
    parser.add_argument("--ack-timeout", type=float, default=None, metavar="S",
                        help="seconds to wait for each tick's HIL_SYNC_ACK (default 10)")


def main(args: argparse.Namespace) -> int:
    """Run the scenario; print the summary; 0 on success."""
    from hil.bus import resolve_bus_config
    from hil.errors import HilError
    from hil.faults import scenario_fault_spec
    from hil.scenario import list_scenarios, load_scenario
    from hil.session import RunOptions, check_c_ecu, run_hil
    from hil.time_master import DEFAULT_ACK_TIMEOUT_S, DEFAULT_HANDSHAKE_TIMEOUT_S

    with bad_option_values():
        for name in ("handshake_timeout", "ack_timeout"):
            value = getattr(args, name)
            if value is not None and not value > 0:
                raise HilError(f"--{name.replace('_', '-')} must be > 0 s, got {value}")
        args.controller = controller_name(args.controller)
        # the ECU's own checks, before anything else (eso-ecu makes them too)
        check_ecu_configuration(args.controller, args.model, args.excite)
    # --scenario naming no file and no shipped scenario is a bad option value, as an unknown
    # --controller; a scenario file that does not load is bad input
    names_nothing = not Path(args.scenario).exists() and args.scenario not in list_scenarios()
    with bad_option_values() if names_nothing else nullcontext():
        scenario = load_scenario(args.scenario)
    plot_file = None if args.plot in (None, SHOW_ONLY) else args.plot
    with bad_option_values():
        check_run_paths(scenario, args.log, args.out, args.replace, model=args.model,
                        excite=args.excite, plot=plot_file)
    options = RunOptions(
        controller=args.controller,
        bus=resolve_bus_config(args.interface, args.channel),
        lockstep=args.lockstep,
        log_path=args.log,
        handshake_timeout_s=args.handshake_timeout or DEFAULT_HANDSHAKE_TIMEOUT_S,
        ack_timeout_s=args.ack_timeout or DEFAULT_ACK_TIMEOUT_S,
        ecu_output=args.out / "ecu_output.txt" if args.out is not None else None,
        faults=scenario_fault_spec(scenario) if args.faults else None,
        model=args.model, excite=args.excite, ecu=args.ecu,
    )
    if args.ecu == "c":
        check_c_ecu(options)  # an executable not built, NMPC, --excite: before --out is made
    if args.out is not None:
        args.out.mkdir(exist_ok=True)
    view = None
    if args.plot is None:
        result = run_hil(scenario, options)
    else:
        from hil.live_view import display_available, run_with_live_view

        interactive = display_available()
        if not interactive and plot_file is None:
            print("note: --plot: no display here (no DISPLAY, or MPLBACKEND is not interactive): "
                  "the run goes on without the live view; --plot FILE.png writes its last frame",
                  file=sys.stderr)
            result = run_hil(scenario, options)
        else:
            result, view = run_with_live_view(scenario, options, interactive)
    summary = result.summary()
    if args.out is not None:
        for path in result.write(args.out):
            print(f"wrote {path}", file=sys.stderr)  # stdout: the JSON summary alone
    if view is not None and plot_file is not None:
        print(f"wrote {view.save(plot_file)}", file=sys.stderr)
    print(json.dumps(summary, indent=2))
    if view is not None:
        if view.interactive:
            print("note: --plot: close the live view's window to end", file=sys.stderr)
            sys.stdout.flush()
        view.hold()
        view.close()
    if summary["active_cycles"] == 0:
        raise HilError(f"the ECU never went ACTIVE in {summary['control_cycles']} control "
                       "cycles (see CTRL_MODE in the log / ecu.csv)")
    if not args.lockstep and summary["realtime_overruns"]:
        share = summary["realtime_overruns"] / max(summary["ticks"], 1)
        print(f"note: {summary['realtime_overruns']} of {summary['ticks']} plant ticks ended after "
              f"their deadline ({share:.0%}): the plant ran slower than real time here",
              file=sys.stderr)
    return 0


@contextmanager
def bad_option_values() -> Iterator[None]:
    """The checks inside look at option values only, so what they refuse is a bad option
    (the message names it): the HIL's and the ECU's errors are re-raised as
    `hil.errors.OptionError`, which ``eso-hil`` exits 2 for, as ``eso-ecu`` does. A DBC
    that does not load (``can_defs``' error) is no option's fault and passes as it is."""
    from firmware_sim.errors import EcuError
    from hil.errors import HilError, OptionError

    try:
        yield
    except OptionError:
        raise
    except (HilError, EcuError) as error:
        raise OptionError(str(error)) from error


def check_ecu_configuration(controller: str, model: Path | None, excite: str | None) -> None:
    """The ECU's checks of ``--model`` and ``--excite`` (``eso-ecu`` makes the same before
    it opens the bus): a controller without model files, a missing file, the other kind of
    model file, a model for study only, a bad excitation program.

    Raises:
        firmware_sim.errors.ConfigError: names the option, the file and what is wrong.
    """
    from firmware_sim.controller_factory import model_controller_factory
    from firmware_sim.excitation import load_excitation

    load_excitation(excite)
    model_controller_factory(controller, model)


#: Files ``hil run --out`` writes into its folder.
OUT_FILES = ("plant.csv", "ecu.csv", "summary.json", "ecu_output.txt")


def check_run_paths(scenario: object, log: Path | None, out: Path | None, replace: bool, *,
                    model: Path | None = None, excite: str | None = None,
                    plot: Path | None = None) -> None:
    """Refuse unusable outputs before the run (issue 17, defects 5 and 6).

    Raises:
        hil.errors.OutputPathError: ``--log`` or ``--out`` is one of the run's inputs (the
            scenario, its path file, the DBC, the ECU's ``--model`` files and ``--excite``
            program file), exists without ``--replace``, is of the
            wrong kind, or its folder is missing or not writable.
        can_defs.errors.DbcLoadError: the DBC does not load.
    """
    from can_defs.codec import prepare
    from can_defs.dbc import DBC_PATH
    from hil.errors import HilError, OutputPathError
    from hil.logio import check_log_suffix, sidecar_path
    from firmware_sim.inputs import command_inputs
    from hil.output_paths import check_not_input, check_output_file, check_output_folder

    prepare()  # a DBC that does not load stops the run here, not in its first frame
    inputs = command_inputs([Path(scenario.source), Path(scenario.path_file)],  # type: ignore[attr-defined]
                            dbc=DBC_PATH, model=model, excite=excite)
    if log is not None:
        check_not_input(log, "--log", inputs)  # the worst case first: an input overwritten
        try:
            check_log_suffix(log)  # only formats the project's own readers read back
        except HilError as error:  # its message starts with the path: say it once
            raise OutputPathError(f"--log {log}: {str(error).removeprefix(f'{log}: ')}") from None
        check_output_file(log, "--log", replace=replace, inputs=inputs)
        check_output_file(sidecar_path(log), "--log (sidecar)", replace=replace, inputs=inputs)
    if out is not None:
        check_output_folder(out, "--out", OUT_FILES, replace=replace, inputs=inputs)
        if log is not None and any(Path(log).resolve() == (out / name).resolve()
                                   for name in OUT_FILES):
            raise OutputPathError(f"--log {log}: is one of the files --out writes")
    if plot is not None:
        from hil.live_view import check_image_path

        check_not_input(plot, "--plot", inputs)
        check_image_path(plot)
        check_output_file(plot, "--plot", replace=replace, inputs=inputs)

"""Command line of the ECU (part of the CAN contract's tooling):

    python -m firmware_sim --interface I --channel C --controller NAME \
        --path ID=FILE.csv [--path ID=FILE.csv ...] (--lockstep | --realtime)

``--interface`` / ``--channel`` default to python-can's configuration chain: the
``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment variables, then the python-can config file.
Bad input prints ``error: ...`` on stderr and exits non-zero (2 for arguments and for
configuration the ECU cannot use at all: an unreadable path file, a DBC that does not
load, a ``--timing-out`` file that cannot be written; 1 for a bus that cannot be opened);
all of it is checked before the bus is opened, and tracebacks only with ``--debug``. The
content of a path file is checked when it is loaded: a bad one latches FAULT (contract).
SIGINT / SIGTERM / SIGHUP send one last STEER_TORQUE_CMD with CMD_VALID = 0, close the
bus, write the timing record and exit 0.

``--model PATH`` builds the controller on another model file (a Koopman artefact for
eso-dkmpc / dkmpc, a fitted bicycle for lmpc / lmpc-eso); ``--excite PROGRAM`` adds an
identification excitation while ACTIVE (``firmware_sim/excitation.py``,
docs/identification.md). Both are checked before the bus is opened. ``--native`` runs the
control step in the C core (``firmware_sim/native.py``, docs/firmware.md), loaded and
checked before the bus is opened too.

Only the arguments and the calls are here; what they call is library code that ``hil``
shares: ``firmware_sim/path_arguments.py`` (``--path``), ``firmware_sim/controller_factory.py``
(``--model``), ``firmware_sim/excitation.py`` (``--excite``), ``firmware_sim/can_bus.py``
(the bus) and ``models/output_paths.py`` (``--timing-out``).
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import NoReturn

from controller.registry import ALL_CONTROLLER_NAMES
from firmware_sim.can_bus import open_ecu_bus
from firmware_sim.config import EcuConfig
from firmware_sim.controller_factory import model_controller_factory
from firmware_sim.errors import BusOpenError, ConfigError, EcuError
from firmware_sim.excitation import load_excitation
from firmware_sim.inputs import command_inputs
from firmware_sim.path_arguments import parse_paths
from models.output_paths import check_output_file

#: ``--controller`` choices: every name the registry builds (the paper's four, the
#: ablations, then the geometric baseline), taken from it so that a new controller is a
#: choice here without a second list. The registry loads a controller's module only when it
#: builds one, so ``--help`` still loads no control law.
CONTROLLER_CHOICES = ALL_CONTROLLER_NAMES
LOG_LEVELS = ("debug", "info", "warning", "error")

EXIT_OK = 0
EXIT_BUS = 1
EXIT_USAGE = 2


class _ArgumentParser(argparse.ArgumentParser):
    """argparse with the project's one ``error: ...`` line and exit 2: no usage text (its
    options fill a screen); argparse's message names the option and, for a choice, the
    valid ones."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"error: {message}; eso-ecu --help lists the options\n")


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``python -m firmware_sim``."""
    parser = _ArgumentParser(
        prog="eso-ecu",
        description="ESO-DKMPC controller ECU on a CAN bus. The bus contract (frames, timing, "
                    "modes, fault reaction) is docs/can-contract.md in the repository.")
    parser.add_argument("--interface", default=None,
                        help="python-can interface (default: CAN_INTERFACE, then python-can's config)")
    parser.add_argument("--channel", default=None,
                        help="python-can channel (default: CAN_CHANNEL, then python-can's config)")
    parser.add_argument("--bitrate", type=int, default=None, help="bit rate, bit/s (interface dependent)")
    parser.add_argument("--controller", required=True, choices=CONTROLLER_CHOICES, type=str.lower,
                        help="control law from the controller registry (any case)")
    parser.add_argument("--path", action="append", required=True, metavar="ID=FILE.csv",
                        help="reference path for PATH_ID (0..255), CSV header x,y,yaw; repeatable")
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--lockstep", action="store_true",
                      help="virtual time from HIL_SYNC (deterministic HIL emulation)")
    mode.add_argument("--realtime", action="store_true", help="monotonic wall clock")
    parser.add_argument("--log-level", default="warning", type=str.lower, choices=LOG_LEVELS,
                        help="logging level on stderr (default warning)")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    parser.add_argument("--cpu", type=int, default=None, metavar="N",
                        help="pin the process to CPU N (benchmarks; skipped with a warning "
                             "where refused)")
    parser.add_argument("--rt-priority", type=int, default=None, metavar="P",
                        help="run under SCHED_FIFO priority P (1..99) where permitted")
    parser.add_argument("--timing-out", type=Path, default=None, metavar="FILE.npz",
                        help="write the per-cycle timing record here on exit (its folder must "
                             "exist; checked at start)")
    parser.add_argument("--replace", action="store_true",
                        help="overwrite an existing --timing-out file")
    parser.add_argument("--model", type=Path, default=None, metavar="PATH",
                        help="another model file: a Koopman artefact (PATH.npz + PATH.json) for "
                             "eso-dkmpc / dkmpc, a fitted bicycle (JSON) for lmpc / lmpc-eso "
                             "(docs/identification.md)")
    parser.add_argument("--native", action="store_true",
                        help="run the control step in the C core build/firmware/libecu.so "
                             "(make firmware; eso-dkmpc, dkmpc, lmpc; docs/firmware.md)")
    parser.add_argument("--excite", default=None, metavar="PROGRAM",
                        help="superimpose an identification excitation while ACTIVE: chirp, prbs, "
                             "steps, prbs-torque, or a .toml / .csv program file "
                             "(docs/identification.md)")
    parser.add_argument("--release", default="clock", metavar="clock|sample",
                        help="what releases the control task: clock (contract revision 2, the "
                             "default) or sample (revision 3: the plant's samples, with the "
                             "period watchdog; docs/can-contract.md)")
    parser.add_argument("--plant-period", type=int, default=10, metavar="MS",
                        help="the plant's sample period: 10 (default) or 25 ms (revision 3, with "
                             "--release sample)")
    parser.add_argument("--dbc", type=Path, default=None, metavar="FILE.dbc",
                        help="CAN matrix to use (default: the contract's can_defs/vehicle.dbc); "
                             "one that does not load is an error before the bus is opened")
    return parser


def make_stop_handler(stop_event: threading.Event) -> Callable[[int, FrameType | None], None]:
    """Signal handler that asks the ECU loop to stop (the loop then closes cleanly)."""
    def handle(signum: int, frame: FrameType | None) -> None:
        stop_event.set()
    return handle


def main(argv: Sequence[str] | None = None, stop_event: threading.Event | None = None) -> int:
    """Run the ECU until SIGINT / SIGTERM (or ``stop_event``); returns the exit status.

    Signal handlers are installed only when called from the main thread; tests that run
    ``main`` in a thread stop it through ``stop_event``.
    """
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop_event = stop_event or threading.Event()
    try:
        paths = parse_paths(args.path)
        config = EcuConfig(control_release=args.release, plant_sample_period_ms=args.plant_period)
        if args.timing_out is not None:
            inputs = command_inputs(paths.values(), dbc=args.dbc, model=args.model, excite=args.excite)
            check_output_file(args.timing_out, "--timing-out", replace=args.replace, inputs=inputs,
                              error=ConfigError)
        prepare_codec(args.dbc)
        excitation = load_excitation(args.excite)
        controller_factory = model_controller_factory(args.controller, args.model)
        if args.native:  # the C core's step in place of the Python one (loaded here)
            from firmware_sim.native import native_controller_factory
            controller_factory = native_controller_factory(args.controller, args.model)
        bus = open_ecu_bus(args.interface, args.channel, args.bitrate)
    except EcuError as error:
        if args.debug:
            raise
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BUS if isinstance(error, BusOpenError) else EXIT_USAGE

    if threading.current_thread() is threading.main_thread():
        handler = make_stop_handler(stop_event)
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(signum, handler)

    if args.cpu is not None or args.rt_priority is not None:
        from firmware_sim.timing import apply_realtime_policy
        try:
            policy = apply_realtime_policy(args.cpu, args.rt_priority)
        except ValueError as error:
            bus.shutdown()
            print(f"error: {error}", file=sys.stderr)
            return EXIT_USAGE
        logging.getLogger("firmware_sim").info("scheduling: %s", policy.describe())
        for note in policy.notes:
            logging.getLogger("firmware_sim").warning("%s", note)

    from firmware_sim.ecu import Ecu  # after argument checks: keeps --help and errors fast
    ecu = None
    try:
        ecu = Ecu(bus, args.controller, paths, lockstep=args.lockstep, config=config,
                  reopen_bus=lambda: open_ecu_bus(args.interface, args.channel, args.bitrate),
                  controller_factory=controller_factory, excitation=excitation)
        if args.realtime:
            # after start-up, before the loop: keeps full collections out of the task's time
            from firmware_sim.timing import freeze_start_up_objects
            logging.getLogger("firmware_sim").info(
                "garbage collector: %d start-up objects frozen", freeze_start_up_objects())
        logging.getLogger("firmware_sim").info(
            "ready: controller %s, PATH_IDs %s, %s, mode %s", args.controller,
            sorted(paths), "lockstep" if args.lockstep else "real time", ecu.mode.name)
        ecu.run(stop_event)
    finally:
        if ecu is not None:
            ecu.close()
        else:
            bus.shutdown()
    if ecu is not None and args.timing_out is not None:
        try:
            ecu.timing.save(args.timing_out)
        except OSError as error:
            if args.debug:
                raise
            print(f"error: --timing-out {args.timing_out}: cannot write the timing record: "
                  f"{error.strerror or error}", file=sys.stderr)
            return EXIT_BUS
    return EXIT_OK


def prepare_codec(dbc: Path | None) -> None:
    """Load the DBC and build the codecs before the bus is opened (issue 17, defect 2).

    Raises:
        ConfigError: the DBC cannot be read or parsed, or lacks a contract frame.
    """
    from can_defs.codec import prepare
    from can_defs.errors import CanDefsError
    try:
        prepare(dbc)
    except CanDefsError as error:
        raise ConfigError(str(error)) from error


def entry() -> None:
    """The ``eso-ecu`` console command (pyproject ``[project.scripts]``): `main` with
    single-threaded BLAS (as ``python -m firmware_sim``: set before numpy loads, which
    happens only once `main` builds the ECU) and a quiet end when stdout's reader closed
    the pipe (exit 141 = 128 + SIGPIPE, no BrokenPipeError traceback)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        status = main()
        sys.stdout.flush()
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        status = 128 + signal.SIGPIPE
    raise SystemExit(status)

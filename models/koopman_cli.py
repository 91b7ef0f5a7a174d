"""The command line of the deep Koopman training, ``python -m models.koopman_train``.

Its arguments (``build_parser``), the checks of its inputs and outputs before any training
(``check_outputs``: ``--out`` given, never an input, an existing artefact only with
``--replace``; each ``--logs`` file bounded), the ``--logs`` output folder and the command
itself (``main``): the data from ``--data`` or ``--logs``, then one path for both (the
settings fitted to the data, ``models.koopman_settings.settings_for_data``; the other
artefact of ``--compare-with``, ``models/koopman_compare.py``; the fit). torch-free: the
training (``models/koopman_train.py``) is imported when the command runs;
``models.koopman_train`` re-exports ``main`` and ``build_parser``.
"""
from __future__ import annotations

import argparse
import copy
import functools
import sys
from pathlib import Path
from typing import Any, Sequence

from models.koopman import DICTIONARY, MODEL_FORMS, KoopmanError
from models.koopman_artifact import save_artifact
from models.koopman_compare import compare_with_reference, load_reference
from models.koopman_data import dataset_hash, load_trajectories
from models.koopman_metrics import OPEN_LOOP_STEPS
from models.koopman_settings import DEFAULT_INPUTS, DEFAULT_STATES, TrainingSettings, settings_for_data
from models.lifted_least_squares import LEAST_SQUARES_FORMS, fit_least_squares
from models.local_lateral_fit import friction_of_runs
from models.range_coverage import coverage_lines, held_out_coverage

#: The description ``--help`` shows (the first line of ``models/koopman_train.py``'s docstring).
DESCRIPTION = "Training of the deep Koopman model in torch (build time only; the ECU never imports this)."


def _names(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("expected a comma-separated list of column names")
    return names


def build_parser() -> argparse.ArgumentParser:
    defaults = TrainingSettings()
    p = argparse.ArgumentParser(prog="python -m models.koopman_train", description=DESCRIPTION)
    p.add_argument("--data", default="data/nominal", help="directory of named-column CSV runs")
    p.add_argument("--out", default=None,
                   help="artefact path without extension (required; with --logs a folder, created if "
                        "missing, whose parent must exist); an existing output is refused "
                        "without --replace")
    p.add_argument("--replace", action="store_true",
                   help="overwrite an existing --out artefact (or the outputs in the --out folder)")
    p.add_argument("--states", type=_names, default=DEFAULT_STATES, help="state columns, comma-separated")
    p.add_argument("--inputs", type=_names, default=DEFAULT_INPUTS, help="input columns, comma-separated")
    p.add_argument("--ts", type=float, default=0.025, help="sample time in s (data are resampled to it)")
    p.add_argument("--features", type=int, default=defaults.n_features, help="d, number of learned features")
    p.add_argument("--seq-len", type=int, default=defaults.seq_len, help="p, sequence length of eq. 9")
    p.add_argument("--epochs", type=int, default=defaults.max_epochs)
    p.add_argument("--steps-per-epoch", type=int, default=defaults.steps_per_epoch)
    p.add_argument("--batch-size", type=int, default=defaults.batch_size)
    p.add_argument("--hidden", type=lambda s: tuple(int(v) for v in s.split(",")), default=defaults.hidden,
                   help="hidden layer widths, comma-separated")
    p.add_argument("--lifted-weight", type=float, default=defaults.lifted_weight)
    p.add_argument("--form", choices=(*MODEL_FORMS, *LEAST_SQUARES_FORMS), default=defaults.form,
                   help="model form: the paper's linear eq. 5, bilinear (input matrix depends on z), "
                        "scheduled over speed (default); or a least-squares lift fitted in closed form "
                        "(edmdc-linear, edmdc-bilinear: the physics dictionary, no learned features, "
                        "models/lifted_least_squares.py)")
    p.add_argument("--dictionary", type=lambda t: tuple(n for n in t.split(",") if n),
                   default=defaults.dictionary,
                   help=f"fixed lifting functions, comma-separated, '' for none (known: {','.join(DICTIONARY)})")
    p.add_argument("--speed-knots", type=lambda t: tuple(float(v) for v in t.split(",")),
                   default=None, help="speed knots in m/s of the scheduled form, comma-separated (default: "
                                      f"those of {list(defaults.speed_knots)} inside the data's speed range, "
                                      "or the range's ends where fewer than two are; --data and --logs alike)")
    p.add_argument("--small-signal-accel", type=float, default=defaults.small_signal_accel, metavar="A0",
                   help="weigh windows by 1 / (1 + (peak |vx r| / A0)^2), A0 in m/s^2; 0 (default) for off")
    p.add_argument("--unscheduled-states", type=lambda t: tuple(n for n in t.split(",") if n),
                   default=defaults.unscheduled_states, metavar="NAMES",
                   help="states whose dynamics row is one for all speed knots (scheduled form), comma-separated")
    p.add_argument("--mirror-symmetric", action="store_true",
                   help="build the left / right mirror symmetry into the model (scheduled form)")
    p.add_argument("--even-features", type=int, default=defaults.even_features,
                   help="with --mirror-symmetric: how many of the d features are even (the rest odd)")
    p.add_argument("--servo-lag", action="store_true",
                   help="with --mirror-symmetric: the wheel-angle row is a lag of unit DC gain from the steer command")
    p.add_argument("--lateral-per-step", action="store_true",
                   help="with --mirror-symmetric: schedule the lateral rows on each step's speed in training")
    p.add_argument("--steer-bilinear", action="store_true",
                   help="with --mirror-symmetric: add a steer-bilinear term, so the steer response depends "
                        "on the state at a given speed")
    p.add_argument("--gain-anchor", type=float, default=defaults.gain_anchor, metavar="W",
                   help="weight of the gain anchor: the small-signal steer response held to local fits of the "
                        "training runs' gentle samples (scheduled form); 0 (default) for off")
    p.add_argument("--gain-anchor-vy", type=float, default=defaults.gain_anchor_vy, metavar="W",
                   help="with --gain-anchor: weight of its lateral-velocity term, the small-signal steer "
                        "response's vy held to the same local fits (error of vy / r in m); 0 (default) for off")
    p.add_argument("--val-runs", type=_names, default=(), metavar="RUN,...",
                   help="runs (file names without .csv) for validation (default: --val-fraction of the runs)")
    p.add_argument("--test-runs", type=_names, default=(), metavar="RUN,...",
                   help="runs held out for the test (default: --test-fraction of the runs)")
    p.add_argument("--val-fraction", type=float, default=defaults.val_fraction,
                   help="share of the runs for validation when --val-runs is not given (0-0.5)")
    p.add_argument("--test-fraction", type=float, default=defaults.test_fraction,
                   help="share of the runs for the test when --test-runs is not given (0-0.5)")
    p.add_argument("--patience", type=int, default=defaults.patience, help="epochs without improvement before stopping")
    p.add_argument("--learning-rate", type=float, default=defaults.learning_rate)
    p.add_argument("--lr-decay", type=float, default=defaults.lr_decay, help="learning-rate factor per epoch")
    p.add_argument("--seed", type=int, default=defaults.seed)
    p.add_argument("--threads", type=int, default=defaults.threads, help="torch CPU threads (part of the result)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=defaults.device)
    p.add_argument("--compare-with", type=Path, default=None, metavar="OTHER.json",
                   help="another artefact: trained with the same settings on the same test runs, its recorded "
                        "test errors must be reproduced within 10%% (exit 3 if not); otherwise (another form, a "
                        "least-squares lift, another seed, ...) OTHER.npz is run on this training's test runs and both "
                        "models' RMSEs are printed side by side. Its states, inputs and ts must be the data's")
    p.add_argument("--logs", type=Path, nargs="+", default=None, metavar="LOG",
                   help="train from CAN logs of the contract's bus (or named-column CSVs with "
                        "--mapping); --out is then a folder (docs/identification.md)")
    p.add_argument("--log-inputs", choices=("command", "measured"), default="command",
                   help="--logs: inputs from STEER_TORQUE_CMD (CMD_VALID = 1) or the measured "
                        "STEER_ANGLE / DRIVE_TORQUE")
    p.add_argument("--mapping", type=Path, default=None, help="--logs: TOML mapping of named-column CSVs")
    p.add_argument("--vehicle", type=Path, default=None,
                   help="--logs: vehicle file of the bicycle's mass and geometry (default models/vehicle.toml)")
    p.add_argument("--dbc", type=Path, default=None, help="--logs: DBC to decode with (default the contract's)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    return p


#: Options of the network's training, which a closed-form least-squares fit has no use for:
#: its lift is the dictionary (no learned features, no knots, no symmetry or anchor terms) and
#: one linear solve in numpy replaces the epochs (no torch threads or device). Given with
#: ``--form edmdc-*`` they are refused rather than ignored. The split (``--seed``, runs,
#: fractions), ``--dictionary``, the data, output and display options apply to both.
DEEP_ONLY_OPTIONS = (
    "--features", "--seq-len", "--epochs", "--steps-per-epoch", "--batch-size", "--hidden",
    "--lifted-weight", "--speed-knots", "--small-signal-accel", "--unscheduled-states",
    "--mirror-symmetric", "--even-features", "--servo-lag", "--lateral-per-step", "--steer-bilinear",
    "--gain-anchor", "--gain-anchor-vy", "--patience", "--learning-rate", "--lr-decay", "--threads", "--device",
)


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> set[str]:
    """The long option strings on the command line ``argv`` (``None``: ``sys.argv[1:]``),
    whichever way argparse accepts them (``--opt=v``, an unambiguous prefix), even when the
    value given is the default: a re-parse in which no option has a default."""
    bare = copy.deepcopy(parser)
    for action in bare._actions:
        action.default = argparse.SUPPRESS
    given = vars(bare.parse_args(argv))
    return {action.option_strings[-1] for action in parser._actions if action.dest in given}


def check_form_options(form: str, given: set[str]) -> None:
    """Refuse the options of ``DEEP_ONLY_OPTIONS`` among ``given`` for a least-squares form.

    Raises:
        KoopmanError: one line naming the first such option and the form.
    """
    if form not in LEAST_SQUARES_FORMS:
        return
    for option in DEEP_ONLY_OPTIONS:
        if option in given:
            raise KoopmanError(f"{option} does not apply to --form {form}: a closed-form least-squares fit of "
                               "the physics dictionary trains no network (drop the option, or choose a "
                               f"deep form: {', '.join(MODEL_FORMS)})")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    defaults = TrainingSettings()
    least_squares = args.form in LEAST_SQUARES_FORMS
    if least_squares:
        fit = functools.partial(_fit_least_squares, form=args.form,
                                dictionary=None if args.dictionary == defaults.dictionary else args.dictionary)
    else:
        from models.koopman_train import train as fit  # torch: only when a network is trained
    try:
        check_form_options(args.form, given_options(parser, argv))
        settings = TrainingSettings(
            n_features=args.features, hidden=args.hidden, seq_len=args.seq_len, batch_size=args.batch_size,
            max_epochs=args.epochs, steps_per_epoch=args.steps_per_epoch, lifted_weight=args.lifted_weight,
            form=defaults.form if least_squares else args.form, dictionary=args.dictionary, patience=args.patience,
            speed_knots=args.speed_knots or defaults.speed_knots, val_runs=args.val_runs,
            test_runs=args.test_runs, val_fraction=args.val_fraction, test_fraction=args.test_fraction, small_signal_accel=args.small_signal_accel,
            unscheduled_states=args.unscheduled_states,
            mirror_symmetric=args.mirror_symmetric, even_features=args.even_features,
            servo_lag=args.servo_lag, lateral_per_step=args.lateral_per_step,
            steer_bilinear=args.steer_bilinear, gain_anchor=args.gain_anchor,
            gain_anchor_vy=args.gain_anchor_vy, learning_rate=args.learning_rate, lr_decay=args.lr_decay,
            seed=args.seed, threads=args.threads, device=args.device,
        )
        check_outputs(args)
        if args.logs:  # issue 20: the data come from CAN logs; --out is a folder
            from models.log_identification import load_log_runs, write_log_products
            out_folder = _log_out_folder(args.out)
            runs, meta, warnings, ts = load_log_runs(args.logs, args.ts, args.log_inputs, args.mapping, args.dbc)
            friction = None
        else:
            data_dir = Path(args.data)
            if not data_dir.is_dir():
                raise KoopmanError(f"data directory not found: {data_dir}")
            runs, ts = load_trajectories(data_dir, args.states, args.inputs, args.ts), args.ts
            meta = {"data_dir": str(data_dir), "data_hash": dataset_hash(data_dir), "n_runs": len(runs)}
            friction = friction_of_runs(data_dir)
        # One path for both sources from here: the options' columns, the knots of the data's speeds.
        settings, notes = settings_for_data(settings, runs, knots_given=args.speed_knots is not None,
                                            closed_form=least_squares)
        for note in notes:
            print(f"note: {note}")
        reference = None if args.compare_with is None else load_reference(args.compare_with, runs, ts)
        result = fit(runs, ts, settings, progress=not args.no_progress, metadata=meta, friction=friction)
        by_name = {run.name: run for run in runs}
        # printed, not kept in the artefact: the artefact of the same data and settings stays the same bytes
        coverage = held_out_coverage(result.model, [by_name[name] for name in result.train_runs],
                                     [by_name[name] for name in result.test_runs]) if result.test_runs else None
        if args.logs:
            npz_path, json_path = save_artifact(out_folder / "koopman", result.learned, result.model.metadata)
            for path in write_log_products(out_folder, result.model, runs, result.test_runs, ts,
                                           args.vehicle, meta, warnings):
                print(f"wrote {path}")
        else:
            npz_path, json_path = save_artifact(args.out, result.learned, result.model.metadata)
    except Exception as e:  # noqa: BLE001 - CLI boundary: one line unless --debug
        if args.debug or not _is_input_error(e):
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    meta = result.model.metadata
    for role in ("train", "validation", "test"):
        print(f"{role} runs ({len(meta['split'][role])}): {', '.join(meta['split'][role])}")
    fitted = "fitted in closed form" if least_squares else f"best epoch {result.best_epoch}"
    print(f"wrote {npz_path} and {json_path} in {result.seconds:.1f} s "
          f"({fitted}, spectral radius of A {meta['spectral_radius_A']:.4f})")
    for name, figures in meta["test_errors"].items():
        print(f"  test {name:>10}: one-step max/avg/rmse {figures['one_step_max']:.4f} / "
              f"{figures['one_step_avg']:.4f} / {figures['one_step_rmse']:.4f}, "
              f"{OPEN_LOOP_STEPS}-step rmse {figures['open_loop_rmse']:.4f}")
    for line in coverage_lines(coverage) if coverage is not None else ():
        print(f"warning: {line}")
    if reference is not None:
        return compare_with_reference(meta, [by_name[name] for name in result.test_runs], reference)
    return 0


def _fit_least_squares(runs: Sequence[Any], ts: float, settings: TrainingSettings, *, form: str,
                       dictionary: tuple[str, ...] | None, progress: bool = True,
                       metadata: dict[str, Any] | None = None, friction: Any = None) -> Any:
    """``train``'s signature for the closed-form fit (progress and friction unused: it takes
    seconds and fits no gain anchor)."""
    return fit_least_squares(runs, ts, form, settings, dictionary=dictionary, metadata=metadata)


#: Files ``--logs --out DIR`` writes into its folder.
LOG_OUTPUTS = ("koopman.npz", "koopman.json", "bicycle.json", "report.json", "report.md")


def check_outputs(args: argparse.Namespace) -> None:
    """Each ``--logs`` file a regular file of at most ``LOG_FILE_MAX_BYTES``; and ``--out``
    before any training (issue 38, item 11): given (no default points at a
    committed artefact), never one of the inputs, and an existing artefact (or, with
    ``--logs``, a folder holding its outputs) only with ``--replace``.

    Raises:
        KoopmanError: naming the option (or the log), the path and the problem.
    """
    from models.errors import OutputPathError
    from models.input_files import LOG_FILE_MAX_BYTES, check_file_size
    from models.output_paths import check_output_file, check_output_folder

    if args.out is None:
        raise KoopmanError("--out is required: the artefact path without extension (with --logs, a folder "
                           "for koopman.npz/.json, bicycle.json, report.md)")
    for log in args.logs or ():   # each log bounded before any reader takes it whole
        if Path(log).exists():    # (a missing one is the log reader's error)
            check_file_size(log, LOG_FILE_MAX_BYTES, KoopmanError)
    out = Path(args.out)
    inputs = [*(args.logs or [Path(args.data)]),
              *(path for path in (args.mapping, args.vehicle, args.dbc, args.compare_with) if path is not None)]
    try:
        if args.logs:
            check_output_folder(out, "--out", LOG_OUTPUTS, replace=args.replace, inputs=inputs)
        else:
            for suffix in (".npz", ".json"):
                check_output_file(out.with_suffix(suffix), "--out", replace=args.replace, inputs=inputs)
    except OutputPathError as error:
        raise KoopmanError(str(error)) from None


def _log_out_folder(out: str | Path) -> Path:
    """``--out`` of ``--logs``: a folder (created; its parent must exist)."""
    folder = Path(out)
    if not folder.parent.is_dir():
        raise KoopmanError(f"--out {folder}: folder {folder.parent} does not exist")
    folder.mkdir(exist_ok=True)
    return folder


def _is_input_error(e: Exception) -> bool:
    from models.errors import ModelError

    return isinstance(e, (ModelError, OSError, ValueError))

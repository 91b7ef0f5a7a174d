"""Hyper-parameters of one deep Koopman training run, and their record in the artefact.

``TrainingSettings`` (validated on construction) and ``settings_json``, the form the
artefact's JSON keeps them in, which studies compare to reuse a trained model; the default
state and input columns of a training. torch-free: the command line
(``models/koopman_cli.py``) takes its defaults from here without torch. The training itself
is ``models/koopman_train.py``.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from models.koopman import DEFAULT_SPEED_KNOTS, DICTIONARY, DICTIONARY_STATES, MODEL_FORMS, KoopmanError

if TYPE_CHECKING:
    from models.koopman_metrics import Trajectory

#: The measured front wheel angle (the steering actuator's state) joins the vehicle states:
#: with it the lift sees the tyres' slip angles and the actuator lag (docs/koopman.md).
DEFAULT_STATES = ("vx", "vy", "yaw_rate", "steer_measured")
DEFAULT_INPUTS = ("torque", "steer")


@dataclass(frozen=True)
class TrainingSettings:
    """Hyper-parameters of one training run (all stored in the artefact's JSON).

    ``seq_len`` is p of eq. 9: p states per sequence, p - 1 predicted steps (31: the MPC's
    horizon of 30). One epoch = ``steps_per_epoch`` Adam steps on batches drawn with
    replacement. ``form``: "linear" (the paper's eq. 5) or "bilinear"; ``dictionary``:
    fixed lifting functions (names of ``models.koopman.DICTIONARY``), () for none.

    Two options of the step-steer study (``studies.step_steer_spread``), off by default:
    ``small_signal_accel`` a0 > 0 weighs each window's prediction error by
    1 / (1 + (a / a0)^2), a the window's peak |vx r| (m/s^2), so windows in the tyres' linear
    range count more than those at the limit; ``unscheduled_states`` names states whose row
    of (A, B, c) is one for all speed knots (the wheel angle: the servo does not depend on
    speed). Both are left out of the artefact's settings record while off, so artefacts
    trained before them still match their settings.

    ``mirror_symmetric`` (scheduled form only) builds the left / right mirror symmetry into
    the model (``models/koopman_train_symmetric.py``): ``even_features`` of the d features
    are even, the rest odd; ``servo_lag`` makes the wheel-angle row a lag of unit DC gain
    from the steer command; ``lateral_per_step`` schedules the lateral rows on each step's
    measured speed in training; ``steer_bilinear`` adds a steer-bilinear term
    (u_steer - u0) N(v) (z - z0) whose N maps even to odd coordinates and back, so the
    response to a steer change depends on the state at a given speed. Recorded only when
    ``mirror_symmetric`` is on (``steer_bilinear`` only when on).

    ``gain_anchor`` w > 0 (scheduled form; recorded only when on) adds
    w times the gain anchor's loss (``models/koopman_train_anchor.py``): the model's
    small-signal steer response held to local fits of the training runs' gentle samples.
    ``gain_anchor_vy`` w > 0 (with ``gain_anchor``; recorded only when on) adds w times the
    anchor's lateral-velocity term: the model's step-steer vy held to local fits at the step's
    amplitude, its error that of vy / r in metres. Recorded with it, ``gain_anchor_vy_fits``
    names those fits' samples (:data:`VY_ANCHOR_FITS`), so that an artefact trained on the
    earlier targets (the gentle samples', before 2026-12-08) does not pass for one of these
    (Table I's model cache compares the settings).
    """

    n_features: int = 5
    hidden: tuple[int, ...] = (96, 96, 96)
    seq_len: int = 31
    batch_size: int = 128
    learning_rate: float = 2e-3
    lr_decay: float = 0.94
    max_epochs: int = 120
    steps_per_epoch: int = 100
    patience: int = 10
    min_delta: float = 0.005
    form: str = "scheduled"
    dictionary: tuple[str, ...] = ()
    speed_knots: tuple[float, ...] = DEFAULT_SPEED_KNOTS
    recon_weight: float = 1.0
    lifted_weight: float = 1.0
    small_signal_accel: float = 0.0
    unscheduled_states: tuple[str, ...] = ()
    mirror_symmetric: bool = False
    even_features: int = 2
    servo_lag: bool = False
    lateral_per_step: bool = False
    steer_bilinear: bool = False
    gain_anchor: float = 0.0
    gain_anchor_vy: float = 0.0
    val_fraction: float = 0.15
    test_fraction: float = 0.15
    val_runs: tuple[str, ...] = ()
    test_runs: tuple[str, ...] = ()
    val_windows: int = 4096
    seed: int = 0
    threads: int = 1
    warm_start: bool = True
    device: str = "auto"

    def __post_init__(self) -> None:
        checks = {
            "n_features": self.n_features >= 1,
            "hidden": len(self.hidden) >= 1 and all(h >= 1 for h in self.hidden),
            "seq_len": self.seq_len >= 2,
            "batch_size": self.batch_size >= 1,
            "learning_rate": self.learning_rate > 0,
            "lr_decay": 0 < self.lr_decay <= 1,
            "max_epochs": self.max_epochs >= 1,
            "steps_per_epoch": self.steps_per_epoch >= 1,
            "patience": self.patience >= 1,
            "min_delta": 0 <= self.min_delta < 1,
            "form": self.form in MODEL_FORMS,
            "speed_knots": len(self.speed_knots) >= 2 and all(b > a for a, b in zip(self.speed_knots, self.speed_knots[1:])),
            "dictionary": all(name in DICTIONARY for name in self.dictionary),
            "threads": self.threads >= 1,
            "recon_weight": self.recon_weight >= 0,
            "lifted_weight": self.lifted_weight >= 0,
            "small_signal_accel": self.small_signal_accel >= 0,
            "unscheduled_states": self.form == "scheduled" or not self.unscheduled_states,
            "mirror_symmetric": self.form == "scheduled" or not self.mirror_symmetric,
            "even_features": 0 <= self.even_features <= self.n_features,
            "servo_lag": self.mirror_symmetric or not self.servo_lag,
            "lateral_per_step": self.mirror_symmetric or not self.lateral_per_step,
            "steer_bilinear": self.mirror_symmetric or not self.steer_bilinear,
            "gain_anchor": self.gain_anchor >= 0 and (self.gain_anchor == 0 or self.form == "scheduled"),
            # The vy targets are the yaw targets times vy / r: they need the yaw anchor's.
            "gain_anchor_vy": self.gain_anchor_vy >= 0 and (self.gain_anchor_vy == 0 or self.gain_anchor > 0),
            "val_fraction": 0 < self.val_fraction < 0.5,
            "val_runs": not set(self.val_runs) & set(self.test_runs),
            "test_fraction": 0 < self.test_fraction < 0.5,
            "device": self.device in ("auto", "cpu", "cuda"),
        }
        for name, ok in checks.items():
            if not ok:
                raise KoopmanError(f"training setting {name}={getattr(self, name)!r} is invalid")


def settings_json(settings: TrainingSettings) -> dict:
    out = asdict(settings)
    out["hidden"] = list(settings.hidden)
    out["dictionary"] = list(settings.dictionary)
    out["speed_knots"] = list(settings.speed_knots)
    out["unscheduled_states"] = list(settings.unscheduled_states)
    # Options added after artefacts were committed: recorded only when on (see the class).
    out["val_runs"], out["test_runs"] = list(settings.val_runs), list(settings.test_runs)
    for name in ("small_signal_accel", "unscheduled_states", "val_runs", "test_runs"):
        if not out[name]:
            del out[name]
    if not settings.mirror_symmetric:
        for name in ("mirror_symmetric", "even_features", "servo_lag", "lateral_per_step"):
            del out[name]
    if not settings.steer_bilinear:
        del out["steer_bilinear"]
    if not settings.gain_anchor:
        del out["gain_anchor"]
    if not settings.gain_anchor_vy:
        del out["gain_anchor_vy"]
    else:
        out["gain_anchor_vy_fits"] = VY_ANCHOR_FITS
    return out


#: How the vy anchor's local fits choose their samples (``models/koopman_train_anchor.py``,
#: ``vy_grip_limit``), recorded in the settings of a training with ``gain_anchor_vy``.
VY_ANCHOR_FITS = "grip use below the step's"


#: Columns an option needs: option -> (states, inputs) that must be among the data's.
OPTION_COLUMNS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "servo_lag": (("steer_measured",), ("steer",)),
    "gain_anchor": (("vx", "vy", "yaw_rate", "steer_measured"), ("torque", "steer")),
    "gain_anchor_vy": (("vx", "vy", "yaw_rate", "steer_measured"), ("torque", "steer")),
}


def missing_columns(settings: TrainingSettings, states: Sequence[str], inputs: Sequence[str]) -> list[str]:
    """One line per option that is on although the data lack a column it needs: the servo
    lag, the gain anchor and its vy term (the mirror symmetry names a column without a
    parity itself, ``models.koopman_train_symmetric.parities``). Empty when every option on
    can run."""
    problems = []
    for option, (needed_states, needed_inputs) in OPTION_COLUMNS.items():
        if not getattr(settings, option):
            continue
        lacking = [n for n in needed_states if n not in states] + [n for n in needed_inputs if n not in inputs]
        if lacking:
            problems.append(f"--{option.replace('_', '-')} needs the column(s) {lacking}, which the data "
                            f"(states {list(states)}, inputs {list(inputs)}) do not have")
    return problems


def knots_in_range(knots: Sequence[float], low: float, high: float) -> tuple[float, ...]:
    """The speed knots for data whose first state (the speed) spans [low, high] m/s: the
    given knots inside the range; where fewer than two are, the range's two ends (a
    scheduled model holds its end knots' models beyond them, so knots the data never reach
    would be fitted on nothing)."""
    inside = tuple(float(k) for k in knots if low <= k <= high)
    if len(inside) >= 2:
        return inside
    if not high > low:
        raise KoopmanError(f"the data's speed spans [{low:g}, {high:g}] m/s: a scheduled model needs a range")
    return (float(low), float(high))


def settings_for_data(settings: TrainingSettings, runs: Sequence["Trajectory"], *, knots_given: bool,
                      closed_form: bool) -> tuple[TrainingSettings, list[str]]:
    """``settings`` fitted to the data of ``runs``, whichever way they were read (``--data``
    runs or ``--logs`` pieces, so both get the same checks and knots): an option on whose
    columns the data lack is refused (``missing_columns``); the scheduled form's speed knots,
    unless given (``knots_given``), are those of ``settings.speed_knots`` inside the range of
    the first state (``knots_in_range``). ``closed_form``: a least-squares fit, which takes
    no knots and chooses its own dictionary. Returns the settings and the notes to print.

    Raises:
        KoopmanError: one line per option on whose columns the data lack, ``;``-joined.
    """
    states, inputs = runs[0].state_names, runs[0].input_names
    problems = missing_columns(settings, states, inputs)
    if problems:
        raise KoopmanError("; ".join(problems))
    notes = []
    if not closed_form and not settings.dictionary and tuple(states[:3]) != DICTIONARY_STATES:
        # The dictionary's formulas are for [vx, vy, yaw_rate]; other data go without it.
        notes.append(f"states {tuple(states)} are not {DICTIONARY_STATES}: training without the dictionary")
    if not closed_form and not knots_given and settings.form == "scheduled":
        speeds = np.concatenate([run.states[:, 0] for run in runs])
        knots = knots_in_range(settings.speed_knots, float(speeds.min()), float(speeds.max()))
        if knots != settings.speed_knots:
            notes.append(f"speed knots {list(knots)} (the data's {states[0]} spans {speeds.min():.2f}-"
                         f"{speeds.max():.2f}; --speed-knots to choose others)")
        settings = dataclasses.replace(settings, speed_knots=knots)
    return settings, notes

"""Controller tuning: frozen dataclasses loaded from ``controller/tuning.toml`` and validated.

One TOML table per controller (``[eso-dkmpc]``, ``[dkmpc]``, ``[lmpc]``, ``[nmpc]``, the
ablations ``[lmpc-eso]``, ``[dmdc-eso]`` and the geometric baseline ``[stanley]``) plus
``[longitudinal]`` for the P speed controller they all share. Every error names the table,
the field and the offending value (``TuningError``). Loading happens at build time only.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar

from controller.errors import TuningError

DEFAULT_TUNING_PATH = Path(__file__).with_name("tuning.toml")

#: Field name -> predicate on the (already type-checked) value, with the rule in words.
_Rule = tuple[Callable[[Any], bool], str]
_POSITIVE: _Rule = (lambda v: v > 0, "must be > 0")
_NON_NEGATIVE: _Rule = (lambda v: v >= 0, "must be >= 0")


@dataclass(frozen=True)
class LongitudinalTuning:
    """P speed controller: torque = speed_gain * (target_speed - vx), clipped to the limits."""

    speed_gain: float
    torque_min: float
    torque_max: float

    def __post_init__(self) -> None:
        if self.torque_min >= self.torque_max:
            raise TuningError(
                f"[longitudinal] torque_min ({self.torque_min}) must be < torque_max ({self.torque_max})"
            )


@dataclass(frozen=True)
class StageWeights:
    """The weights of eq. 15 that the speed schedule moves: Q on X and Y error, Q on yaw
    error, R on the steer angle (p_steer_rate, the normalisation, is not scheduled)."""

    q_position: float
    q_yaw: float
    r_steer: float


@dataclass(frozen=True)
class MpcTuning:
    """Weights and horizons shared by the four steering MPCs (eq. 15).

    ``state_min`` / ``state_max`` are eq. 21's bounds on [vx, vy, yaw_rate], enforced softly.

    Speed schedule of the weights (:meth:`weights_at`): at and below
    ``weight_schedule_speeds[0]`` (m/s) the MPC uses ``low_speed_q_position``,
    ``low_speed_q_yaw``, ``low_speed_r_steer``; at and above ``weight_schedule_speeds[1]``
    ``q_position``, ``q_yaw``, ``r_steer``; linearly in the measured vx between. With the
    low-speed weights equal to the others there is no schedule (the paper's fixed weights).

    Heading target (``controller.steady_slip``): ``slip_target_limit`` (rad; 0: off) bounds
    the measured side slip vy / vx by which the yaw cost's target moves, so that the cost
    holds the course (heading plus slip) on the path; ``slip_target_gate`` (rad) is the bend
    of the horizon's reference at which that target has faded to zero.

    Actuator terms (issue 37; both 0 = off, the default, and optional in the TOML):
    ``qp_steer_rate_limit`` (rad/s) adds the hard rows |U_j - U_(j-1)| <= limit * Ts over
    the Nc moves (U_(-1) the previous command) to the steering QP
    (``controller.steering_qp``); the steering actuator's own rate is the plant's
    ``[actuators] steer_rate_limit`` (models/vehicle.toml, 1.0 rad/s).
    ``delay_compensation_s`` (s) is the fixed part of the delay from a sample to the
    command's effect (the actuator's dead time plus the expected task time); with it on, the
    QP MPCs predict the measured state forward over it plus the sample's age
    (``VehicleSample.sample_age_s``) through their own model with the commands already sent
    (``controller.delay_compensation``). Not tuned: turning either on is the tuning's job.

    ``pose_heading_advance`` (steps, optional in the TOML): the heading along which each
    step of the horizon's pose moves, yaw_i + advance * Ts * r_i
    (``controller.pose_kinematics``). 0, the default, is eq. 20's explicit Euler; 0.5 the
    step's midpoint, exact for a constant yaw rate (docs/controllers.md, "The pose step").

    Grip envelope (``controller.grip_envelope``, optional in the TOML): with
    ``grip_slip_excess`` > 0 (rad; 0: off, the default) the MPCs bound the yaw rate by
    (1 + ``grip_margin``) a_max / vx, a_max the road's grip as estimated from the rear
    axle's slip beyond the nominal bicycle's linear need (``grip_slip_excess``), the recent
    peak of the lateral acceleration (memory ``grip_peak_time``, s) and a return to no bound
    at ``grip_recovery`` (m/s^2 per s) once the rear axle grips again.
    """

    prediction_horizon: int
    control_horizon: int
    q_position: float
    q_yaw: float
    r_steer: float
    p_steer_rate: float
    state_min: tuple[float, float, float]
    state_max: tuple[float, float, float]
    slack_l1: float
    slack_l2: float
    low_speed_q_position: float
    low_speed_q_yaw: float
    low_speed_r_steer: float
    weight_schedule_speeds: tuple[float, float]
    slip_target_limit: float
    slip_target_gate: float
    # Keyword-only with a default, so that they may follow the subclasses' required fields
    # and stay optional in the TOML (0: off, every committed table).
    qp_steer_rate_limit: float = field(default=0.0, kw_only=True)
    delay_compensation_s: float = field(default=0.0, kw_only=True)
    pose_heading_advance: float = field(default=0.0, kw_only=True)
    grip_slip_excess: float = field(default=0.0, kw_only=True)
    grip_margin: float = field(default=0.1, kw_only=True)
    grip_recovery: float = field(default=10.0, kw_only=True)
    grip_peak_time: float = field(default=1.0, kw_only=True)

    def __post_init__(self) -> None:
        low, high = self.weight_schedule_speeds
        if not 0.0 <= low < high:
            raise TuningError(
                f"weight_schedule_speeds must be two speeds 0 <= low < high (m/s), got [{low}, {high}]"
            )
        if self.control_horizon > self.prediction_horizon:
            raise TuningError(
                f"control_horizon ({self.control_horizon}) must be <= prediction_horizon "
                f"({self.prediction_horizon})"
            )
        for name, low, high in zip(("vx", "vy", "yaw_rate"), self.state_min, self.state_max):
            if low >= high:
                raise TuningError(f"state_min[{name}] ({low}) must be < state_max[{name}] ({high})")

    def weights_at(self, vx: float) -> StageWeights:
        """The scheduled weights at measured speed ``vx`` (m/s); held for the whole horizon.

        The C core computes the same (firmware/src/ecu_qp.c, ``use_weights``)."""
        low, high = self.weight_schedule_speeds
        # Fraction of the way from the low-speed weights to the others; a NaN speed never
        # reaches here (the MPC falls back on a non-finite sample first).
        blend = min(max((vx - low) / (high - low), 0.0), 1.0)
        return StageWeights(
            q_position=self.low_speed_q_position + blend * (self.q_position - self.low_speed_q_position),
            q_yaw=self.low_speed_q_yaw + blend * (self.q_yaw - self.low_speed_q_yaw),
            r_steer=self.low_speed_r_steer + blend * (self.r_steer - self.low_speed_r_steer),
        )


@dataclass(frozen=True)
class QpMpcTuning(MpcTuning):
    """MPC solved as one OSQP QP per step (LMPC, DKMPC)."""

    osqp_max_iter: int
    osqp_eps_abs: float
    osqp_eps_rel: float


@dataclass(frozen=True)
class EsoDkmpcTuning(QpMpcTuning):
    """ESO-DKMPC: the QP MPC plus the ESO.

    The gains beta1, beta2 of eq. 13 (g1 = g2 = identity) follow from
    ``models.eso.design_gains(A, eso_pole, second_pole=eso_second_pole)``: the two error
    poles of eq. 24 in every lifted direction (a fast one lets z_hat follow z, a slow one
    sets how quickly w_hat moves). ``disturbance_decay`` shapes w_hat over the horizon:
    step i of the prediction adds ``disturbance_decay**i * w_hat``; 1 holds it constant,
    as eq. 15 does. ``eso_innovation_limit`` bounds the innovation that moves w_hat in one
    step (``models.eso.InnovationSaturation`` on the vy and yaw-rate entries, m/s and
    rad/s; 0: no bound). ``eso_innovation_persistence`` widens that bound while the
    innovation stays beyond it with one sign (``models.eso.PersistentInnovationBound``: by
    the limit once per that many steps, up to 4 times the limit; 0: a fixed bound), on
    steps whose measured lateral acceleration |vx r| is below ``eso_widening_lateral_accel``
    (m/s^2; 0: on every step).
    ``yaw_rate_bias_pole`` is the pole of the yaw-rate sensor bias estimate from the heading
    (``models.yaw_rate_bias``; 1: no estimate).
    """

    eso_pole: float
    eso_second_pole: float
    disturbance_decay: float
    eso_innovation_limit: float
    eso_innovation_persistence: float
    eso_widening_lateral_accel: float
    yaw_rate_bias_pole: float


#: The same fields for every QP MPC with the eq. 13 observer: ESO-DKMPC and the ablations
#: ``lmpc-eso`` (the observer on LMPC's bicycle) and ``dmdc-eso`` (on a DMDc model).
EsoQpMpcTuning = EsoDkmpcTuning


@dataclass(frozen=True)
class NmpcTuning(MpcTuning):
    """NMPC solved to convergence by IPOPT."""

    ipopt_max_iter: int
    ipopt_tol: float

    def __post_init__(self) -> None:
        super().__post_init__()
        # NMPC has no QP and no delay compensation (yet): refuse rather than ignore.
        for name in ("qp_steer_rate_limit", "delay_compensation_s", "pose_heading_advance"):
            if getattr(self, name) != 0.0:
                raise TuningError(f"{name} must be 0 for NMPC (not implemented there), got {getattr(self, name)!r}")


@dataclass(frozen=True)
class StanleyTuning:
    """The geometric Stanley law (``controller/stanley.py``; Hoffmann et al. 2007).

    steer = -heading_error - atan(cross_track_gain e_fa / (softening_speed + vx))
            + yaw_rate_gain (vx kappa - yaw_rate),

    with e_fa the signed cross-track error of the front axle (m, left positive), kappa the
    path curvature at its foot point (1/m). The result passes a first-order low-pass of
    time constant ``steer_time_constant`` (s; 0: none), then a rate limit of
    ``steer_rate_limit`` (rad/s), then the steering limit.
    """

    cross_track_gain: float
    softening_speed: float
    yaw_rate_gain: float
    steer_rate_limit: float
    steer_time_constant: float


@dataclass(frozen=True)
class ControllerTuning:
    """The whole tuning file."""

    longitudinal: LongitudinalTuning
    eso_dkmpc: EsoDkmpcTuning
    dkmpc: QpMpcTuning
    lmpc: QpMpcTuning
    nmpc: NmpcTuning
    lmpc_eso: EsoQpMpcTuning
    dmdc_eso: EsoQpMpcTuning
    stanley: StanleyTuning

    def for_controller(self, name: str) -> MpcTuning | StanleyTuning:
        """The table of registry name ``name`` (e.g. ``"eso-dkmpc"``)."""
        table = {"eso-dkmpc": self.eso_dkmpc, "dkmpc": self.dkmpc, "lmpc": self.lmpc,
                 "nmpc": self.nmpc, "lmpc-eso": self.lmpc_eso, "dmdc-eso": self.dmdc_eso,
                 "stanley": self.stanley}
        if name not in table:
            raise TuningError(f"no tuning table for controller {name!r}")
        return table[name]


#: The scheduled weights and their low-speed fields (MpcTuning.weights_at).
SCHEDULED_WEIGHTS = ("q_position", "q_yaw", "r_steer")
LOW_SPEED_WEIGHTS = tuple(f"low_speed_{name}" for name in SCHEDULED_WEIGHTS)

_Table = TypeVar("_Table", bound=MpcTuning)


def low_speed_twins(weights: Mapping[str, float]) -> dict[str, float]:
    """The low-speed weights that a flat schedule adds to ``weights`` (tuning fields to
    values): ``low_speed_<name>`` equal to each scheduled weight given whose twin is not
    given itself (an explicit low-speed weight wins), in ``SCHEDULED_WEIGHTS`` order."""
    return {f"low_speed_{name}": weights[name] for name in SCHEDULED_WEIGHTS
            if name in weights and f"low_speed_{name}" not in weights}


def with_fixed_weights(table: _Table, **weights: float) -> _Table:
    """``table`` with ``weights`` (fields of eq. 15's weights, e.g. ``q_position=10``) at
    every speed: each scheduled weight given also replaces its low-speed twin, unless that
    twin is given too (``low_speed_q_position=...``). Other fields (``p_steer_rate``,
    observer fields) pass through as given."""
    return replace(table, **weights, **low_speed_twins(weights))


_RULES: dict[str, _Rule] = {
    "speed_gain": _POSITIVE,
    "prediction_horizon": (lambda v: 2 <= v <= 200, "must be in [2, 200]"),
    "control_horizon": (lambda v: 1 <= v <= 50, "must be in [1, 50]"),
    "q_position": _NON_NEGATIVE,
    "q_yaw": _NON_NEGATIVE,
    "r_steer": _POSITIVE,
    "low_speed_q_position": _NON_NEGATIVE,
    "low_speed_q_yaw": _NON_NEGATIVE,
    "low_speed_r_steer": _POSITIVE,
    "p_steer_rate": _NON_NEGATIVE,
    "slack_l1": _POSITIVE,
    "slack_l2": _POSITIVE,
    "osqp_max_iter": (lambda v: v >= 1, "must be >= 1"),
    "osqp_eps_abs": _POSITIVE,
    "osqp_eps_rel": _NON_NEGATIVE,
    "ipopt_max_iter": (lambda v: v >= 1, "must be >= 1"),
    "ipopt_tol": _POSITIVE,
    "eso_pole": (lambda v: 0.0 <= v < 1.0, "must be in [0, 1)"),
    "eso_second_pole": (lambda v: 0.0 <= v < 1.0, "must be in [0, 1)"),
    "disturbance_decay": (lambda v: 0.0 <= v <= 1.0, "must be in [0, 1]"),
    "eso_innovation_limit": (lambda v: 0.0 <= v <= 10.0, "must be in [0, 10] (0: no bound)"),
    "eso_innovation_persistence": (lambda v: 0.0 <= v <= 1000.0, "must be in [0, 1000] steps (0: a fixed bound)"),
    "eso_widening_lateral_accel": (lambda v: 0.0 <= v <= 20.0, "must be in [0, 20] m/s^2 (0: no gate)"),
    "yaw_rate_bias_pole": (lambda v: 0.0 <= v <= 1.0, "must be in [0, 1] (1: no estimate)"),
    "slip_target_limit": (lambda v: 0.0 <= v <= 0.2, "must be in [0, 0.2] rad (0: off)"),
    "slip_target_gate": (lambda v: 0.0 < v <= 1.0, "must be in (0, 1] rad"),
    "cross_track_gain": _POSITIVE,
    "softening_speed": _POSITIVE,
    "yaw_rate_gain": _NON_NEGATIVE,
    "steer_rate_limit": _POSITIVE,
    "steer_time_constant": _NON_NEGATIVE,
    # The C core's reader (firmware/src/ecu_data.c, read_tuning) applies the same two ranges.
    "qp_steer_rate_limit": (lambda v: 0.0 <= v <= 100.0, "must be in [0, 100] rad/s (0: off)"),
    "delay_compensation_s": (lambda v: 0.0 <= v <= 0.1, "must be in [0, 0.1] s (0: off)"),
    "pose_heading_advance": (lambda v: v in (0.0, 0.5), "must be 0 (eq. 20, explicit Euler) or 0.5 (the step's midpoint)"),
    # The grip envelope (controller.grip_envelope); the C core's reader applies the same ranges.
    "grip_slip_excess": (lambda v: 0.0 <= v <= 0.2, "must be in [0, 0.2] rad (0: off)"),
    "grip_margin": (lambda v: 0.0 <= v <= 2.0, "must be in [0, 2]"),
    "grip_recovery": (lambda v: 0.0 < v <= 1000.0, "must be in (0, 1000] m/s^2 per s"),
    "grip_peak_time": (lambda v: 0.0 < v <= 60.0, "must be in (0, 60] s"),
}


def _convert(table: str, name: str, annotation: str, value: Any) -> Any:
    """Type-check one TOML value against the dataclass annotation (as a string)."""
    where = f"[{table}] {name}"
    if annotation == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise TuningError(f"{where} must be an integer, got {value!r}")
        return value
    if annotation == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise TuningError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if annotation == "tuple[float, float]":
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           and math.isfinite(v) for v in value)):
            raise TuningError(f"{where} must be a list of 2 finite numbers [low, high], got {value!r}")
        return tuple(float(v) for v in value)
    if annotation.startswith("tuple[float"):
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           and math.isfinite(v) for v in value)):
            raise TuningError(f"{where} must be a list of 3 finite numbers [vx, vy, yaw_rate], got {value!r}")
        return tuple(float(v) for v in value)
    raise TypeError(f"unsupported annotation {annotation}")  # programming error, not input


def _build(cls: type, table_name: str, table: Any) -> Any:
    """Build dataclass ``cls`` from TOML table ``table``: no missing, unknown or bad fields."""
    if not isinstance(table, dict):
        raise TuningError(f"[{table_name}] must be a table, got {table!r}")
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise TuningError(f"[{table_name}] unknown field(s) {unknown}; expected {names}")
    # Fields with a default (the actuator terms, 0 = off) may be left out.
    missing = [f.name for f in fields(cls) if f.name not in table and f.default is MISSING]
    if missing:
        raise TuningError(f"[{table_name}] missing field(s) {missing}")
    values = {}
    for f in fields(cls):
        if f.name not in table:
            continue
        value = _convert(table_name, f.name, str(f.type), table[f.name])
        rule = _RULES.get(f.name)
        if rule is not None and not rule[0](value):
            raise TuningError(f"[{table_name}] {f.name} {rule[1]}, got {value!r}")
        values[f.name] = value
    try:
        return cls(**values)
    except TuningError as e:
        raise TuningError(f"[{table_name}] {e}") from e


def parse_tuning(document: dict[str, Any]) -> ControllerTuning:
    """Validate a parsed TOML document (dict) into ``ControllerTuning``."""
    expected = {"longitudinal", "eso-dkmpc", "dkmpc", "lmpc", "nmpc", "lmpc-eso", "dmdc-eso", "stanley"}
    unknown = sorted(set(document) - expected)
    if unknown:
        raise TuningError(f"unknown table(s) {unknown}; expected {sorted(expected)}")
    missing = sorted(expected - set(document))
    if missing:
        raise TuningError(f"missing table(s) {missing}")
    tuning = ControllerTuning(
        longitudinal=_build(LongitudinalTuning, "longitudinal", document["longitudinal"]),
        eso_dkmpc=_build(EsoDkmpcTuning, "eso-dkmpc", document["eso-dkmpc"]),
        dkmpc=_build(QpMpcTuning, "dkmpc", document["dkmpc"]),
        lmpc=_build(QpMpcTuning, "lmpc", document["lmpc"]),
        nmpc=_build(NmpcTuning, "nmpc", document["nmpc"]),
        lmpc_eso=_build(EsoQpMpcTuning, "lmpc-eso", document["lmpc-eso"]),
        dmdc_eso=_build(EsoQpMpcTuning, "dmdc-eso", document["dmdc-eso"]),
        stanley=_build(StanleyTuning, "stanley", document["stanley"]),
    )
    # LMPC-ESO's forward prediction would need its observer's estimate per step on the
    # bicycle: not implemented, so refused rather than run without it.
    if tuning.lmpc_eso.delay_compensation_s != 0.0:
        raise TuningError(f"[lmpc-eso] delay_compensation_s must be 0 (not implemented for LMPC-ESO), "
                          f"got {tuning.lmpc_eso.delay_compensation_s!r}")
    return tuning


def load_tuning(path: str | Path | None = None) -> ControllerTuning:
    """Load and validate the tuning TOML (default ``controller/tuning.toml``)."""
    path = Path(path) if path is not None else DEFAULT_TUNING_PATH
    try:
        with path.open("rb") as handle:
            document = tomllib.load(handle)
    except FileNotFoundError as e:
        raise TuningError(f"{path}: tuning file not found") from e
    except tomllib.TOMLDecodeError as e:
        raise TuningError(f"{path}: not valid TOML: {e}") from e
    try:
        return parse_tuning(document)
    except TuningError as e:
        raise TuningError(f"{path}: {e}") from e

"""Write the ECU's data file: tuning, Koopman model and bicycle in one compact binary.

The C core (firmware/src) reads this file at start-up instead of parsing TOML, JSON and
.npz itself: the Python packages load and validate the sources (``controller.tuning``,
``models.koopman.KoopmanModel.load``, ``models.bicycle``) and fold the normalisation
exactly as the Python controllers do, so both implementations step on the same numbers.

Layout (little-endian): the magic ``ECUDATA1``, a uint32 record count, then per record a
48-byte NUL-padded name, a uint32 rank, four uint32 dimensions (unused ones 1) and the
float64 values in C order. The C loader (firmware/src/ecu_data.c) checks every record's
shape against the build's (build/firmware/gen/ecu_build.h) and names both on a mismatch.

    python firmware/tools/ecu_data.py --out build/firmware/ecu_data.bin \
        [--tuning controller/tuning.toml] [--model models/artifacts/dk_d5.npz] \
        [--bicycle BICYCLE.json]

The scheduled form with a bilinear term (``KoopmanModel.scheduled_bilinear``, the mirror
form's steer-bilinear N(v)) has its own form code (``SCHEDULED_BILINEAR``) and a record
"koopman.N" (K, n_z, n_z): the steer input's N per knot in physical units. The C core
implements the steer's N only: a model whose torque slice N[:, 0] is not zero is refused.

``--bicycle``: a fitted bicycle (models/bicycle_fit.py's JSON, ``models.bicycle_fit.
load_bicycle_params``) in the "bicycle" record instead of the nominal one, for LMPC; the
file's nonlinear fields are not in the record (LMPC's linear bicycle does not use them).
The grip envelope's rear axle ("grip.axle": mass, lf, lr, Cr) is always the nominal one
(``controller.grip_envelope.RearAxle.nominal``), as in the Python ECU.
"""
from __future__ import annotations

import argparse
import struct
import sys
from pathlib import Path

import numpy as np

from controller.errors import ControllerError
from controller.lifted_mpc import MEASURED_STATES
from controller.registry import check_ecu_model_ts
from controller.tuning import ControllerTuning, load_tuning
from controller.grip_envelope import RearAxle
from models.bicycle import NominalModelParams, nominal_model_params
from models.errors import ModelError
from models.koopman import DEFAULT_ARTIFACT, KoopmanModel

MAGIC = b"ECUDATA1"
NAME_BYTES = 48
#: The QP controllers the C core implements, in the order of its controller ids.
QP_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: Order of VehicleSample's fields (controller.base), as the C core's ecu_sample_t.
SAMPLE_FIELDS = ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque", "target_speed")
#: Dictionary functions by the C core's code (models.koopman.DICTIONARY names).
DICTIONARY_CODES = {"vy/vx": 0, "r/vx": 1, "vx*r": 2, "vx^2/100": 3}
#: Model forms by the C core's code; the (unscheduled) bilinear form is not in the C core.
FORM_CODES = {"linear": 0, "scheduled": 2}
#: The C core's code of the scheduled form with its steer-bilinear term N(v).
SCHEDULED_BILINEAR = 3
#: The input whose bilinear term the C core implements (the steer; the torque's N is zero).
BILINEAR_INPUT = 1
#: Fields of one "tuning.<controller>" record, in order (NaN where a table lacks one).
TUNING_FIELDS = ("prediction_horizon", "control_horizon", "q_position", "q_yaw", "r_steer",
                 "p_steer_rate", "state_min", "state_max", "slack_l1", "slack_l2",
                 "osqp_max_iter", "osqp_eps_abs", "osqp_eps_rel", "eso_pole", "eso_second_pole",
                 "disturbance_decay", "low_speed_q_position", "low_speed_q_yaw", "low_speed_r_steer",
                 "weight_schedule_speeds", "eso_innovation_limit", "yaw_rate_bias_pole",
                 "slip_target_limit", "slip_target_gate", "qp_steer_rate_limit", "delay_compensation_s",
                 "eso_innovation_persistence", "eso_widening_lateral_accel", "pose_heading_advance",
                 "grip_slip_excess", "grip_margin", "grip_recovery", "grip_peak_time")


class EcuDataError(Exception):
    """A source cannot be expressed in the C core's data file."""


def tuning_vector(tuning: ControllerTuning, name: str) -> np.ndarray:
    """The 38 numbers of controller ``name``'s table in TUNING_FIELDS order (state bounds 3 each)."""
    table = tuning.for_controller(name)
    values: list[float] = []
    for field in TUNING_FIELDS:
        value = getattr(table, field, float("nan"))
        values.extend(value if isinstance(value, tuple) else [value])
    return np.array(values, dtype=float)


def form_code(model: KoopmanModel) -> int:
    """The C core's code of ``model``'s form (-1: none of the C core's)."""
    if model.scheduled_bilinear:
        return SCHEDULED_BILINEAR
    return FORM_CODES.get(model.form, -1)


def model_records(model: KoopmanModel) -> dict[str, np.ndarray]:
    """The Koopman model in physical units (normalisation folded, as the Python ECU uses it)."""
    if model.form not in FORM_CODES:
        raise EcuDataError(f"model form {model.form!r}: the C core implements {', '.join(FORM_CODES)}"
                           " (and the scheduled form's steer-bilinear term)")
    if model.scheduled_bilinear:
        # The C core holds the steer's N only: its drift takes the torque column of B(v) as is.
        others = [name for j, name in enumerate(model.input_names)
                  if j != BILINEAR_INPUT and np.any(model.N_knots[:, j] != 0.0)]
        if others:
            raise EcuDataError(f"the scheduled model's bilinear term N(v) of {', '.join(others)} is not zero: "
                               f"the C core implements the bilinear term of the steer only")
    unknown = [n for n in model.state_names if n not in MEASURED_STATES]
    if unknown:
        raise EcuDataError(f"model states {unknown} are not measured by the ECU")
    if model.form == "scheduled":
        knots, a, b, offset = model.speed_knots, model.A_knots, model.B_knots, model.offset_knots
    else:
        knots, a, b, offset = np.zeros(1), model.A[None], model.B[None], model.offset[None]
    records = {
        "koopman.form": np.array([form_code(model)], dtype=float),
        "koopman.knots": np.asarray(knots, dtype=float),
        "koopman.A": a, "koopman.B": b, "koopman.offset": offset,
        "koopman.state_fields": np.array([SAMPLE_FIELDS.index(MEASURED_STATES[n]) for n in model.state_names],
                                         dtype=float),
        "koopman.dictionary": np.array([DICTIONARY_CODES[n] for n in model.dictionary], dtype=float),
    }
    if model.scheduled_bilinear:  # the steer's N(v) per knot, physical units
        records["koopman.N"] = np.ascontiguousarray(model.N_knots[:, BILINEAR_INPUT])
    for i, (w, bias) in enumerate(model._layers):  # the encoder on physical x, folded (read only)
        records[f"koopman.w{i}"] = w
        records[f"koopman.b{i}"] = bias
    return records


def bicycle_params(bicycle_path: Path | None) -> NominalModelParams:
    """The nominal bicycle, or the fitted one of ``bicycle_path`` (BicycleFitError names
    the file and the field)."""
    if bicycle_path is None:
        return nominal_model_params()
    from models.bicycle_fit import load_bicycle_params
    return load_bicycle_params(bicycle_path)


def collect(tuning_path: Path | None, model_path: Path, bicycle_path: Path | None = None) -> dict[str, np.ndarray]:
    """Every record of the data file, by name (``bicycle_path``: a fitted bicycle for LMPC)."""
    tuning = load_tuning(tuning_path)
    model = KoopmanModel.load(model_path)
    check_ecu_model_ts(model.ts, str(Path(model_path).with_suffix(".json")))  # as the C core's reader
    bicycle = bicycle_params(bicycle_path)
    records: dict[str, np.ndarray] = {
        "ts": np.array([model.ts]),
        "longitudinal": np.array([tuning.longitudinal.speed_gain, tuning.longitudinal.torque_min,
                                  tuning.longitudinal.torque_max]),
        "bicycle": np.array([bicycle.cornering_stiffness_front, bicycle.cornering_stiffness_rear,
                             bicycle.mass, bicycle.yaw_inertia, bicycle.lf, bicycle.lr]),
    }
    # The grip envelope's rear axle is always the nominal one, as in the Python ECU, whatever
    # bicycle LMPC gets.
    axle = RearAxle.nominal()
    records["grip.axle"] = np.array([axle.mass, axle.lf, axle.lr, axle.cornering_stiffness_rear])
    for name in QP_CONTROLLERS:
        records[f"tuning.{name}"] = tuning_vector(tuning, name)
    records.update(model_records(model))
    return records


def write_data(records: dict[str, np.ndarray], out: Path) -> None:
    """Write ``records`` in the layout of the module docstring."""
    chunks = [MAGIC, struct.pack("<I", len(records))]
    for name, values in records.items():
        values = np.ascontiguousarray(values, dtype="<f8")
        if values.ndim > 4 or len(name) >= NAME_BYTES:
            raise EcuDataError(f"record {name}: rank {values.ndim} or name too long")
        dims = list(values.shape) + [1] * (4 - values.ndim)
        chunks.append(name.encode("ascii").ljust(NAME_BYTES, b"\0"))
        chunks.append(struct.pack("<5I", values.ndim, *dims))
        chunks.append(values.tobytes())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(b"".join(chunks))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="data file to write")
    parser.add_argument("--tuning", type=Path, default=None, help="tuning TOML (default controller/tuning.toml)")
    parser.add_argument("--model", type=Path, default=DEFAULT_ARTIFACT, help="Koopman artefact (.npz + .json)")
    parser.add_argument("--bicycle", type=Path, default=None,
                        help="fitted bicycle JSON (models/bicycle_fit.py) for LMPC; default the nominal one")
    args = parser.parse_args(argv)
    try:
        write_data(collect(args.tuning, args.model, args.bicycle), args.out)
    except (EcuDataError, ControllerError, ModelError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

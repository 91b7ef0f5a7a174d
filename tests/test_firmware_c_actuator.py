"""The actuator terms of the steering QP (issue 37): the steer-rate rows, in Python and in
the C core, and both loaders' verdicts on the new tuning fields.

The pose step's heading advance rides along (a twin case of its own below), and so do the
grip envelope's fields in the loaders' verdicts (its twin: tests/test_firmware_c_core.py).

With ``qp_steer_rate_limit`` on, the QP's pattern changes (Nc more rows), so the C core is
generated for a tuning file with it on: ``make firmware FW_DIR=build/firmware-actuator
FW_TUNING=build/firmware-actuator/tuning.toml`` (a no-op when up to date; ``build/firmware``
is not touched). Its core then steps beside the Python controller on dlc_smoke with
tests/test_firmware_c_core.py's twin and tolerances (tests/c_twin.py).
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller.errors import TuningError
from controller.registry import create_controller
from controller.steering_qp import SteeringQp
from controller.tuning import DEFAULT_TUNING_PATH, load_tuning, parse_tuning
from c_twin import native_on, requires_c_toolchain, run_twin_on_dlc_smoke

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "build" / "firmware-actuator"
TUNING = BUILD / "tuning.toml"
QP_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: rad/s: below the lane change's own peak steer rate (about 0.16 rad/s on dlc_high_mu), so
#: that the rows bind.
RATE_LIMIT = 0.1
TS = 0.025


def tuning_text(fields: dict[str, float], tables: tuple[str, ...] = QP_CONTROLLERS) -> str:
    """controller/tuning.toml with ``fields`` added to each of ``tables``."""
    lines = []
    for line in DEFAULT_TUNING_PATH.read_text().splitlines(keepends=True):
        lines.append(line)
        if line.strip() in {f"[{t}]" for t in tables}:
            lines.extend(f"{name} = {value!r}\n" for name, value in fields.items())
    return "".join(lines)


def write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` unless ``path`` holds it (a rewrite would rebuild the firmware)."""
    if not path.is_file() or path.read_text() != text:
        path.write_text(text)


# ------------------------------------------------------------------ the loaders' verdicts

def _document(fields: dict[str, object], table: str = "dkmpc") -> dict:
    import tomllib

    document = tomllib.loads(DEFAULT_TUNING_PATH.read_text())
    document[table].update(fields)
    return document


def test_the_actuator_terms_default_off() -> None:
    tuning = load_tuning()
    for name in QP_CONTROLLERS + ("nmpc", "lmpc-eso", "dmdc-eso"):
        table = tuning.for_controller(name)
        assert table.qp_steer_rate_limit == 0.0 and table.delay_compensation_s == 0.0


@pytest.mark.parametrize("fields, message", [
    ({"qp_steer_rate_limit": -0.5}, "qp_steer_rate_limit must be in [0, 100]"),
    ({"qp_steer_rate_limit": 1000.0}, "qp_steer_rate_limit must be in [0, 100]"),
    ({"qp_steer_rate_limit": True}, "qp_steer_rate_limit must be a finite number"),
    ({"qp_steer_rate_limit": "1.0"}, "qp_steer_rate_limit must be a finite number"),
    ({"delay_compensation_s": 0.5}, "delay_compensation_s must be in [0, 0.1]"),
    ({"delay_compensation_s": -0.01}, "delay_compensation_s must be in [0, 0.1]"),
    ({"pose_heading_advance": 0.25}, "pose_heading_advance must be 0 .eq. 20, explicit Euler. or 0.5"),
    ({"pose_heading_advance": -0.5}, "pose_heading_advance must be 0 .eq. 20, explicit Euler. or 0.5"),
    ({"grip_slip_excess": 0.25}, "grip_slip_excess must be in [0, 0.2] rad .0: off., got 0.25"),
    ({"grip_slip_excess": -0.01}, "grip_slip_excess must be in [0, 0.2] rad .0: off., got -0.01"),
    ({"grip_margin": 2.5}, "grip_margin must be in [0, 2], got 2.5"),
    ({"grip_recovery": 0.0}, "grip_recovery must be in .0, 1000] m/s.2 per s, got 0.0"),
    ({"grip_peak_time": 61.0}, "grip_peak_time must be in .0, 60] s, got 61.0"),
])
def test_python_loader_refuses_bad_actuator_terms(fields: dict, message: str) -> None:
    with pytest.raises(TuningError, match=message.replace("[", r"\[")):
        parse_tuning(_document(fields))


def test_nmpc_refuses_the_actuator_terms() -> None:
    with pytest.raises(TuningError, match="must be 0 for NMPC"):
        parse_tuning(_document({"qp_steer_rate_limit": 1.0}, "nmpc"))
    with pytest.raises(TuningError, match="pose_heading_advance must be 0 for NMPC"):
        parse_tuning(_document({"pose_heading_advance": 0.5}, "nmpc"))
    # The grip envelope is NMPC's too (its yaw-rate rows: tests/test_grip_envelope.py).
    assert parse_tuning(_document({"grip_slip_excess": 0.05}, "nmpc")).nmpc.grip_slip_excess == 0.05


# ------------------------------------------------------------------ the rate rows in Python

def test_rate_rows_off_leave_the_problem_as_it_was() -> None:
    table = load_tuning().dkmpc
    off, on = SteeringQp(table), SteeringQp(dataclasses.replace(table, qp_steer_rate_limit=1.0))
    n_ctrl = table.control_horizon
    assert on._lower.size == off._lower.size + n_ctrl
    assert on._a_data.size == off._a_data.size + 2 * n_ctrl - 1


def test_rate_rows_hold_the_increments() -> None:
    """A large position error asks for a fast move: every increment, U_0 - U_{-1} included,
    stays within the limit (to OSQP's eps_abs)."""
    table = dataclasses.replace(load_tuning().dkmpc, qp_steer_rate_limit=RATE_LIMIT)
    qp = SteeringQp(table)
    n_pred, n_ctrl = table.prediction_horizon, table.control_horizon
    jacobian = np.zeros((n_pred, 3, n_ctrl))
    jacobian[:, 1, :] = np.tril(np.ones((n_pred, n_ctrl)))  # each move shifts Y at later steps
    offset = np.zeros((n_pred, 3))
    offset[:, 1] = -2.0
    gain, free = np.zeros((n_pred, 3, n_ctrl)), np.zeros((n_pred, 3))
    previous = 0.05
    solution = qp.solve(jacobian, offset, previous, gain, free, np.full(n_ctrl, previous))
    steps = np.diff(np.concatenate(([previous], solution.steer)))
    print("largest increment", np.max(np.abs(steps)), "limit", RATE_LIMIT * TS)
    assert np.max(np.abs(steps)) <= RATE_LIMIT * TS + table.osqp_eps_abs
    assert np.max(np.abs(steps)) >= 0.9 * RATE_LIMIT * TS  # the rows bind


# ------------------------------------------------------------------ the C core's twin

@pytest.fixture(scope="module")
def actuator_build() -> Path:
    """The firmware generated for the tuning with the rate rows on (build/firmware-actuator)."""
    BUILD.mkdir(parents=True, exist_ok=True)
    write_if_changed(TUNING, tuning_text({"qp_steer_rate_limit": RATE_LIMIT}))
    done = subprocess.run(["make", "-s", "--no-print-directory", "-o", ".venv/.installed", "firmware",
                           f"FW_DIR={BUILD.relative_to(ROOT)}", f"FW_TUNING={TUNING.relative_to(ROOT)}"],
                          cwd=ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    return BUILD


@pytest.fixture(scope="module")
def actuator_core(actuator_build: Path):
    yield from native_on(actuator_build / "libecu.so")


@requires_c_toolchain
@pytest.mark.parametrize("name", QP_CONTROLLERS)
def test_rate_rows_c_step_equals_python_in_closed_loop(actuator_core, name: str) -> None:
    """With the rate rows on: the C core and the Python controller give the same commands
    to 1e-9 rad, status, iterations, predictions and cost on dlc_smoke."""
    twin, _ = run_twin_on_dlc_smoke(name, create_controller(name, tuning_path=TUNING),
                                    actuator_core.NativeController(name, BUILD / "ecu_data.bin"))
    commands = np.array([pair[0].steer_angle for pair in twin.pairs])
    assert np.max(np.abs(np.diff(commands))) <= RATE_LIMIT * TS + 1e-3


@requires_c_toolchain
@pytest.mark.parametrize("field, value, message", [
    ("qp_steer_rate_limit", -0.5, "qp_steer_rate_limit must be in [0, 100] rad/s"),
    ("delay_compensation_s", 0.5, "delay_compensation_s must be in [0, 0.1] s"),
    ("pose_heading_advance", 0.25, "pose_heading_advance must be 0 .eq. 20, explicit Euler. or 0.5"),
    ("grip_slip_excess", 0.25, "grip_slip_excess must be in [0, 0.2] rad .0: off., got 0.25"),
    ("grip_margin", -0.5, "grip_margin must be in [0, 2], got -0.5"),
    ("grip_recovery", 1500.0, "grip_recovery must be in .0, 1000] m/s.2 per s, got 1500.0"),
    ("grip_peak_time", 0.0, "grip_peak_time must be in .0, 60] s, got 0.0"),
])
def test_c_loader_refuses_what_python_refuses(actuator_core, tmp_path: Path, field: str, value: float,
                                              message: str) -> None:
    """The data file written with a value the Python loader refuses: the C core's reader
    refuses it too, naming the field and the range (the grip envelope's fields: with the
    Python loader's message word for word)."""
    sys.path.insert(0, str(ROOT / "firmware" / "tools"))
    from ecu_data import TUNING_FIELDS, collect, write_data  # noqa: E402 (the build tool)

    records = collect(TUNING, ROOT / "models" / "artifacts" / "dk_d5")
    record = records["tuning.dkmpc"]
    # The field's value: every field after the state bounds and the schedule speeds is a
    # scalar (38 values for 31 + 2 fields), so it sits as far from the record's end as the
    # field from TUNING_FIELDS' end.
    assert record.size == 38 and len(TUNING_FIELDS) == 33
    index = record.size - len(TUNING_FIELDS) + TUNING_FIELDS.index(field)
    record[index] = value
    bad = tmp_path / "ecu_data.bin"
    write_data(records, bad)
    with pytest.raises(Exception, match=message.replace("[", r"\[")) as c_error:
        actuator_core.NativeController("dkmpc", bad)
    with pytest.raises(TuningError, match=message.replace("[", r"\[")) as python_error:
        parse_tuning(_document({field: value}))
    if field.startswith("grip_"):
        assert str(python_error.value) in str(c_error.value)


@requires_c_toolchain
def test_the_grip_axle_is_the_nominal_one_with_a_fitted_bicycle_and_its_record_is_required(
        actuator_core, tmp_path: Path) -> None:
    """A fitted bicycle for LMPC (ecu_data.py --bicycle) replaces the bicycle record only:
    the grip envelope's rear axle stays the nominal one, as in the Python ECU; a data file
    without the grip.axle record is refused, naming it."""
    sys.path.insert(0, str(ROOT / "firmware" / "tools"))
    from ecu_data import collect, write_data  # noqa: E402 (the build tool)

    import json

    from controller.grip_envelope import RearAxle
    from models.bicycle import nominal_model_params
    from models.bicycle_fit import BICYCLE_FIELDS, BICYCLE_FILE_KIND

    nominal = RearAxle.nominal()
    values = {name: getattr(nominal_model_params(), name) for name in BICYCLE_FIELDS}
    values.update(mass=nominal.mass + 300.0, cornering_stiffness_rear=0.8 * nominal.cornering_stiffness_rear)
    fitted = tmp_path / "bicycle.json"
    fitted.write_text(json.dumps({"kind": BICYCLE_FILE_KIND, **values}))
    records = collect(TUNING, ROOT / "models" / "artifacts" / "dk_d5", fitted)
    assert records["bicycle"][2] == nominal.mass + 300.0
    assert records["grip.axle"].tolist() == [nominal.mass, nominal.lf, nominal.lr, nominal.cornering_stiffness_rear]
    missing = tmp_path / "no_axle.bin"
    write_data({k: v for k, v in records.items() if k != "grip.axle"}, missing)
    with pytest.raises(Exception, match="no_axle.bin: record grip.axle missing"):
        actuator_core.NativeController("dkmpc", missing)


# ------------------------------------------------------------------ delay compensation's twin

#: s: above one period with the age, so that the window has a whole step and a fraction.
DELAY = 0.03


class AgedNativeController:
    """The C core of ``native`` stepped with the sample's age (``ecu_step_aged``): the
    NativeController's step with its ``ecu_step`` call routed to the aged one."""

    def __init__(self, native, name: str, data: Path) -> None:
        import ctypes

        self.inner = native.NativeController(name, data)
        self.name = name
        library = self.inner._lib
        library.ecu_step_aged.argtypes = [ctypes.POINTER(native._Sample), ctypes.c_double,
                                          ctypes.POINTER(native._Output)]
        library.ecu_step_aged.restype = None

        class _Aged:  # the library with ecu_step taking this step's age
            age = 0.0

            def __getattr__(self, attribute: str):
                return getattr(library, attribute)

            def ecu_step(self, raw, out) -> None:
                library.ecu_step_aged(raw, ctypes.c_double(self.age), out)

        self._aged = _Aged()
        self.inner._lib = self._aged

    def set_path(self, path) -> None:
        self.inner.set_path(path)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, sample):
        self._aged.age = sample.sample_age_s
        return self.inner.step(sample)


#: The twins stepped with the sample's age, each on the rate rows' tuning plus its fields,
#: and the fields of a run that must command differently (the fields acted).
AGED_TWINS = {
    # delay compensation: 30 ms plus the sample's age of 0 or 5 ms
    "delay": ({"delay_compensation_s": DELAY}, {}),
    # the pose's midpoint heading, over the horizon and over the delay window
    "midpoint": ({"delay_compensation_s": DELAY, "pose_heading_advance": 0.5}, {"delay_compensation_s": DELAY}),
}


@requires_c_toolchain
@pytest.mark.parametrize("case", sorted(AGED_TWINS))
@pytest.mark.parametrize("name", QP_CONTROLLERS)
def test_aged_c_step_equals_python_in_closed_loop(actuator_core, name: str, case: str) -> None:
    """With the rate rows and each case's fields on: the C core equals the Python controller
    step for step on dlc_smoke (commands to 1e-9 rad, status, iterations, predictions and
    cost), NaN samples included; and the fields acted (without them the commands differ)."""
    sys.path.insert(0, str(ROOT / "firmware" / "tools"))
    from ecu_data import collect, write_data  # noqa: E402 (the build tool)
    from hil.scenario import load_scenario
    from studies.closed_loop import run_closed_loop
    from studies.delay_compensation import AgedSamples
    from c_twin import INVALID_STEPS
    from test_firmware_c_core import Twin, assert_twin_steps_equal

    fields, without = AGED_TWINS[case]
    tuning, baseline = BUILD / f"tuning_{case}.toml", BUILD / f"tuning_{case}_without.toml"
    write_if_changed(tuning, tuning_text({"qp_steer_rate_limit": RATE_LIMIT, **fields}))
    write_if_changed(baseline, tuning_text({"qp_steer_rate_limit": RATE_LIMIT, **without}))
    data = BUILD / f"ecu_data_{case}.bin"
    write_data(collect(tuning, ROOT / "models" / "artifacts" / "dk_d5"), data)
    twin = Twin(create_controller(name, tuning_path=tuning), AgedNativeController(actuator_core, name, data),
                INVALID_STEPS)
    result = run_closed_loop(load_scenario("dlc_smoke"), AgedSamples(twin))
    assert result.completed, result.failure
    assert_twin_steps_equal(name, twin)
    plain = run_closed_loop(load_scenario("dlc_smoke"), AgedSamples(create_controller(name, tuning_path=baseline)))
    assert np.max(np.abs(plain.trace.steer_cmd - result.trace.steer_cmd)) > 1e-4

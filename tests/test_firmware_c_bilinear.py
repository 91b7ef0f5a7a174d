"""The C core's scheduled form with the steer-bilinear term N(v) against the Python controllers.

Shapes are compile-time, so a second firmware is built for a model of this form: a small
scheduled bilinear artefact (numpy only, below) written into ``build/firmware-bilinear``
and ``make firmware FW_DIR=build/firmware-bilinear FW_MODEL=...`` (a no-op when up to
date; ``build/firmware`` is not touched). Its core then steps beside the Python controller
on the same artefact inside the closed loop of dlc_smoke, as tests/test_firmware_c_core.py
does for the committed model (its twin and tolerances), and refuses data files of the
plain scheduled form or without the N record, naming the problem.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from controller.registry import create_controller
from firmware_sim.errors import ConfigError
from models.bicycle import LinearBicycle
from models.koopman import KoopmanModel, MinMaxScaling, NormalisedKoopman, save_artifact
from c_twin import firmware_for, native_on, replace_unless_same, requires_c_toolchain, run_twin_on_dlc_smoke
from test_firmware_c_core import _tool
from test_firmware_c_core import native  # noqa: F401 (the fixture: the default firmware built)

pytestmark = requires_c_toolchain

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "build" / "firmware-bilinear"
#: The test artefact (without .npz/.json), the build's FW_MODEL.
MODEL = BUILD / "scheduled_bilinear"

TS = 0.025
STATES = ("vx", "vy", "yaw_rate", "steer_measured")  # as models/artifacts/dk_d5.json
INPUTS = ("torque", "steer")
#: dlc_smoke runs at 9.7 m/s: between the knots 8 and 12, so N(v) is interpolated.
KNOTS = (4.0, 8.0, 12.0, 16.0)
#: Encoder widths: 10 outputs take both paths of the C core's blocked lift (8 + 2).
WIDTHS = (10, 3)
STATE_SCALING = MinMaxScaling(np.array([2.0, -6.5, -1.0, -0.3]), np.array([36.0, 8.0, 1.2, 0.3]))
INPUT_SCALING = MinMaxScaling(np.array([-3000.0, -0.3]), np.array([3000.0, 0.3]))
SERVO_TIME_CONSTANT_S = 0.05
WHEEL_RADIUS_M = 0.3
#: Typical magnitudes of z = [vx, vy, r, steer, Phi] (N z changes the steer gain by ~tens of %).
TYPICAL_Z = np.array([10.0, 0.5, 0.5, 0.1, 1.0, 1.0, 1.0])


def _expm(m: np.ndarray) -> np.ndarray:
    """exp(m) by scaling and squaring of a Taylor series (numpy only)."""
    norm = np.abs(m).sum(axis=0).max()
    squarings = int(np.ceil(np.log2(norm / 0.25))) if norm > 0.25 else 0
    scaled, out, term = m / 2.0 ** squarings, np.eye(len(m)), np.eye(len(m))
    for k in range(1, 20):
        term = term @ scaled / k
        out = out + term
    for _ in range(squarings):
        out = out @ out
    return out


def physical_model(bilinear: bool, seed: int = 0) -> tuple[list, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A model that steers like the plant, in physical units: per knot the nominal linear
    bicycle (vy, r) driven by the wheel angle, a first-order steer servo, vx from the torque,
    three encoder features weakly coupled in, and (``bilinear``) the steer's N(v) on the
    lateral rows. Returns (encoder on physical x, A (K, n_z, n_z), B (K, n_z, 2), offset
    (K, n_z), N (K, 2, n_z, n_z) with N[:, 0] = 0, or None)."""
    rng = np.random.default_rng(seed)
    bicycle = LinearBicycle()
    n_x, d = len(STATES), WIDTHS[-1]
    n_z = n_x + d
    encoder = [(0.5 * rng.standard_normal((WIDTHS[0], n_x)) / TYPICAL_Z[:n_x], 0.1 * rng.standard_normal(WIDTHS[0])),
               (0.5 * rng.standard_normal((d, WIDTHS[0])), 0.1 * rng.standard_normal(d))]
    features_from_x = 0.01 * rng.standard_normal((d, n_x)) / TYPICAL_Z[:n_x]
    lateral_from_features = 1e-3 * rng.standard_normal((2, d))
    A, B, offset, N = [], [], [], []
    for v in KNOTS:
        a_lat, b_lat = bicycle.continuous_matrices(v)
        continuous = np.zeros((4, 4))  # [vy, r, steer_measured; steer command]
        continuous[:2, :2], continuous[:2, 2:3] = a_lat, b_lat
        continuous[2, 2], continuous[2, 3] = -1.0 / SERVO_TIME_CONSTANT_S, 1.0 / SERVO_TIME_CONSTANT_S
        discrete = _expm(continuous * TS)
        a, b, c = np.zeros((n_z, n_z)), np.zeros((n_z, 2)), np.zeros(n_z)
        a[0, 0], b[0, 0], c[0] = 1.0, TS / (bicycle.params.mass * WHEEL_RADIUS_M), -0.002 * v
        a[1:4, 1:4], b[1:4, 1] = discrete[:3, :3], discrete[:3, 3]
        a[n_x:, n_x:] = 0.95 * np.eye(d)
        a[n_x:, :n_x] = features_from_x
        a[1:3, n_x:] = lateral_from_features
        n = np.zeros((2, n_z, n_z))
        n[1, 1:3] = 0.4 * rng.uniform(-1.0, 1.0, (2, n_z)) * np.abs(b[1:3, 1])[:, None] / TYPICAL_Z
        A.append(a)
        B.append(b)
        offset.append(c)
        N.append(n)
    return encoder, np.array(A), np.array(B), np.array(offset), np.array(N) if bilinear else None


def normalised(encoder: list, A: np.ndarray, B: np.ndarray, offset: np.ndarray,
               N: np.ndarray | None) -> NormalisedKoopman:
    """The learned quantities (normalised units) whose ``to_physical`` is the given model:
    NormalisedKoopman.to_physical's folding solved for A_n, B_n, affine_n, N_n and the
    encoder's first layer, knot by knot (no dictionary: z_n = [x_n; Phi])."""
    n_z = A.shape[-1]
    n_x = len(STATES)
    s = np.concatenate([STATE_SCALING.high - STATE_SCALING.low, np.ones(n_z - n_x)])
    s_vec = np.concatenate([STATE_SCALING.low, np.zeros(n_z - n_x)])
    d_u, c_u = INPUT_SCALING.scale, INPUT_SCALING.shift
    A_n, B_n, affine_n, N_n = [], [], [], []
    for k in range(len(KNOTS)):
        m = np.zeros((2, n_z, n_z)) if N is None else N[k] / d_u[:, None, None]  # S N_n,j S^-1
        A_n.append((A[k] - np.einsum("j,jab->ab", c_u, m)) * s[None, :] / s[:, None])
        b_n = (B[k] / d_u[None, :] + (m @ s_vec).T) / s[:, None]
        B_n.append(b_n)
        affine_n.append((offset[k] - s_vec + A[k] @ s_vec - s * (b_n @ c_u)) / s)
        N_n.append(m * s[None, None, :] / s[None, :, None])
    w0, b0 = encoder[0]
    w0_n = w0 / STATE_SCALING.scale[None, :]
    return NormalisedKoopman(encoder=((w0_n, b0 - w0_n @ STATE_SCALING.shift), encoder[1]), A_n=np.array(A_n),
                             B_n=np.array(B_n), state_scaling=STATE_SCALING, input_scaling=INPUT_SCALING,
                             N_n=None if N is None else np.array(N_n), affine_n=np.array(affine_n),
                             speed_knots=KNOTS)


def write_artefact(path: Path, bilinear: bool = True) -> KoopmanModel:
    """The test artefact at ``path`` (.npz + .json), left as it is when its content is the
    same (np.savez stamps the time: a rewrite would rebuild the firmware every run)."""
    physical = physical_model(bilinear)
    staging = path.parent / f".{path.name}-new"
    save_artifact(staging, normalised(*physical), {"ts": TS, "state_names": list(STATES),
                                                   "input_names": list(INPUTS)})
    replace_unless_same(staging, path)
    model = KoopmanModel.load(path)
    # the folding round-trips: the loaded model is the physical one designed above
    _, A, B, offset, N = physical
    assert np.abs(model.A_knots - A).max() < 1e-12 and np.abs(model.B_knots - B).max() < 1e-12
    assert np.abs(model.offset_knots - offset).max() < 1e-12
    assert model.scheduled_bilinear == bilinear
    if bilinear:
        assert np.abs(model.N_knots - N).max() < 1e-12 and not np.any(model.N_knots[:, 0])
    return model


@pytest.fixture(scope="module")
def bilinear_build() -> Path:
    """The firmware for the test artefact (build/firmware-bilinear), up to date."""
    return firmware_for(MODEL, write_artefact)


@pytest.fixture(scope="module")
def bilinear_core(bilinear_build: Path):
    """firmware_sim.native on the bilinear build's libecu.so (native_on)."""
    yield from native_on(bilinear_build / "libecu.so")


def test_the_build_is_for_the_steer_bilinear_form(bilinear_build: Path) -> None:
    header = (bilinear_build / "gen" / "ecu_build.h").read_text()
    assert "#define ECU_BILINEAR 1\n" in header and "#define ECU_FORM 3\n" in header
    assert f"#define ECU_NK {len(KNOTS)}\n" in header and f"#define ECU_NZ {len(STATES) + WIDTHS[-1]}\n" in header


@pytest.mark.parametrize("name", ["eso-dkmpc", "dkmpc"])
def test_bilinear_step_equals_python_in_closed_loop(bilinear_core, name: str, tmp_path: Path) -> None:
    """On dlc_smoke (160 steps, 3 of them with a NaN sample): the C core of the bilinear
    build and the Python controller on the same artefact give the same commands to 1e-9
    rad, status, iterations, predictions and cost (assert_twin_steps_equal); and N(v)
    matters here: the same model without it steers otherwise by far more than that."""
    from hil.scenario import load_scenario
    from studies.closed_loop import run_closed_loop

    python = create_controller(name, model_path=MODEL)
    assert python.model.scheduled_bilinear
    twin, result = run_twin_on_dlc_smoke(name, python, bilinear_core.NativeController(name, BUILD / "ecu_data.bin"))
    if name == "eso-dkmpc":  # the observer restarts on the first valid sample after NaN
        assert twin.pairs[42][3].observer_reset and twin.pairs[0][3].observer_reset
    # the same model without its bilinear term: another closed loop, other commands
    write_artefact(tmp_path / "plain", bilinear=False)
    without = run_closed_loop(load_scenario("dlc_smoke"), create_controller(name, model_path=tmp_path / "plain"))
    change = np.abs(without.trace.steer_cmd - result.trace.steer_cmd).max()
    print(f"{name}: largest steer change without N(v) {change:.2e} rad")
    assert change > 1e-5


def test_bilinear_build_refuses_data_without_the_steer_term(bilinear_core, tmp_path: Path) -> None:
    """A plain scheduled model of the same shapes, or the bilinear one without koopman.N or
    with an N of another shape: refused, naming the form or the record."""
    ecu_data = _tool("ecu_data")
    records = ecu_data.collect(None, MODEL)
    assert np.array_equal(records["koopman.N"], KoopmanModel.load(MODEL).N_knots[:, 1])
    n_knots, n_z = records["koopman.A"].shape[:2]
    write_artefact(tmp_path / "plain", bilinear=False)
    ecu_data.write_data(ecu_data.collect(None, tmp_path / "plain"), tmp_path / "plain.bin")
    with pytest.raises(ConfigError) as error:
        bilinear_core.NativeController("dkmpc", tmp_path / "plain.bin")
    message = str(error.value)
    print(message)
    assert (f"the model's shape (form scheduled, {n_knots} knots, n_z {n_z}) differs from this build's "
            f"(form scheduled bilinear, {n_knots} knots, n_z {n_z})") in message
    assert "record koopman.form is 2, this build needs 3" in message
    ecu_data.write_data({k: v for k, v in records.items() if k != "koopman.N"}, tmp_path / "no_n.bin")
    with pytest.raises(ConfigError, match=r"no_n.bin: record koopman.N missing \(this build is for the scheduled "
                                          r"form with the steer-bilinear term N\(v\)\)"):
        bilinear_core.NativeController("eso-dkmpc", tmp_path / "no_n.bin")
    ecu_data.write_data(dict(records, **{"koopman.N": np.zeros((n_knots, n_z, n_z + 1))}), tmp_path / "wide_n.bin")
    with pytest.raises(ConfigError, match=fr"record koopman.N has shape \({n_knots},{n_z},{n_z + 1}\), "
                                          fr"this build needs \({n_knots},{n_z},{n_z}\)"):
        bilinear_core.NativeController("dkmpc", tmp_path / "wide_n.bin")
    bilinear_core.NativeController("dkmpc", BUILD / "ecu_data.bin")  # its own data file still loads


def test_default_build_refuses_data_of_the_other_form(native, tmp_path: Path) -> None:  # noqa: F811 (fixture)
    """The committed model's build: a data file of its shapes but of the other scheduled
    form (plain for a bilinear build, bilinear for a plain one) is refused by the
    executable, both forms named."""
    ecu_data = _tool("ecu_data")
    records = ecu_data.collect(None, ecu_data.DEFAULT_ARTIFACT)
    n_knots, n_z = records["koopman.A"].shape[:2]
    bilinear_build = "#define ECU_BILINEAR 1\n" in (ROOT / "build" / "firmware" / "gen" / "ecu_build.h").read_text()
    assert bilinear_build == KoopmanModel.load().scheduled_bilinear  # the build follows the default artefact
    if bilinear_build:
        records = {k: v for k, v in records.items() if k != "koopman.N"}
        records["koopman.form"] = np.array([ecu_data.FORM_CODES["scheduled"]], dtype=float)
        shown, built, codes = "scheduled", "scheduled bilinear", (2, 3)
    else:
        records.update({"koopman.form": np.array([ecu_data.SCHEDULED_BILINEAR], dtype=float),
                        "koopman.N": np.zeros((n_knots, n_z, n_z))})
        shown, built, codes = "scheduled bilinear", "scheduled", (3, 2)
    ecu_data.write_data(records, tmp_path / "other.bin")
    result = subprocess.run([str(ROOT / "build" / "firmware" / "ecu"), "--controller", "dkmpc", "--path",
                             "1=hil/paths/dlc.csv", "--data", str(tmp_path / "other.bin")], cwd=ROOT,
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    line = result.stderr.strip().splitlines()[-1]
    assert (f"the model's shape (form {shown}, {n_knots} knots, n_z {n_z}) differs from this build's "
            f"(form {built}, {n_knots} knots, n_z {n_z}): record koopman.form is {codes[0]}, "
            f"this build needs {codes[1]}") in line

"""The C core built for an edmdc-linear model (a least-squares lift: a dictionary, no encoder
layers) against the Python controllers.

Shapes are compile-time, so a firmware is built for such a model: a small edmdc-linear
artefact fitted in closed form on synthetic runs, written into ``build/firmware-edmdc``, and
``make firmware FW_DIR=build/firmware-edmdc FW_MODEL=...`` (a no-op when up to date;
``build/firmware`` is not touched). Its core then steps beside the Python controller on the
same artefact inside the closed loop of dlc_smoke, with tests/test_firmware_c_core.py's twin
and tolerances.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from controller.registry import create_controller
from models.koopman import KoopmanModel
from models.koopman_artifact import save_artifact
from models.koopman_settings import TrainingSettings
from models.lifted_least_squares import fit_least_squares
from c_twin import firmware_for, native_on, replace_unless_same, requires_c_toolchain, run_twin_on_dlc_smoke
from test_koopman_synthetic import synthetic_runs

pytestmark = requires_c_toolchain

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "build" / "firmware-edmdc"
#: The test artefact (without .npz/.json), the build's FW_MODEL.
MODEL = BUILD / "edmdc_linear"
TS = 0.025


def write_artefact(path: Path) -> KoopmanModel:
    """An edmdc-linear artefact at ``path`` (.npz + .json), fitted on synthetic runs."""
    result = fit_least_squares(synthetic_runs(n_runs=6, n_samples=300, seed=3), TS, "edmdc-linear",
                               TrainingSettings())
    staging = path.parent / f".{path.name}-new"
    save_artifact(staging, result.learned, result.model.metadata)
    replace_unless_same(staging, path)
    model = KoopmanModel.load(path)
    assert model.form == "linear" and model.n_features == 0 and model.dictionary  # a lift without an encoder
    return model


@pytest.fixture(scope="module")
def edmdc_build() -> Path:
    """The firmware for the test artefact (build/firmware-edmdc), up to date."""
    return firmware_for(MODEL, write_artefact)


@pytest.fixture(scope="module")
def edmdc_core(edmdc_build: Path):
    """firmware_sim.native on the edmdc build's libecu.so (native_on)."""
    yield from native_on(edmdc_build / "libecu.so")


def test_the_build_has_no_encoder_layers(edmdc_build: Path) -> None:
    header = (edmdc_build / "gen" / "ecu_build.h").read_text()
    assert "#define ECU_N_LAYERS 0\n" in header and "#define ECU_FORM 0\n" in header


@pytest.mark.parametrize("name", ["eso-dkmpc", "dkmpc"])
def test_edmdc_linear_step_equals_python_in_closed_loop(edmdc_core, name: str) -> None:
    """On dlc_smoke (160 steps, 3 of them with a NaN sample): the C core of the edmdc-linear
    build and the Python controller on the same artefact give the same commands to 1e-9 rad,
    status, iterations, predictions and cost (assert_twin_steps_equal)."""
    run_twin_on_dlc_smoke(name, create_controller(name, model_path=MODEL),
                          edmdc_core.NativeController(name, BUILD / "ecu_data.bin"))

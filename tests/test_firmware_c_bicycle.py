"""A fitted bicycle for the C ECU's LMPC: firmware/tools/ecu_data.py --bicycle writes it
into the data file, ``--native --model`` and ``hil run --ecu c --model`` convert it, and
the C LMPC with it steers as the Python LMPC with the same bicycle (the equivalence rule:
equal, or 1 LSB in at most 1 % of the frames)."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller.reference import ReferencePath
from controller.registry import create_controller
from models.bicycle import nominal_model_params
from models.bicycle_fit import BICYCLE_FIELDS
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built, libecu.so loaded)
from test_firmware_c_equivalence import compare_runs

ROOT = Path(__file__).resolve().parent.parent
#: A bicycle unlike the nominal one (softer tyres, more yaw inertia), as a fit could give.
CHANGES = {"cornering_stiffness_front": 0.7, "cornering_stiffness_rear": 0.8, "yaw_inertia": 1.25}


def fitted_bicycle(tmp_path: Path, **override: object) -> Path:
    """A bicycle file of models/bicycle_fit.py's form (kind linear_bicycle)."""
    nominal = nominal_model_params()
    fields = {name: float(getattr(nominal, name)) * CHANGES.get(name, 1.0) for name in BICYCLE_FIELDS}
    path = tmp_path / "bicycle.json"
    path.write_text(json.dumps({"kind": "linear_bicycle", "format": 1, **fields, **override}))
    return path


def test_c_lmpc_with_a_fitted_bicycle_steps_as_the_python_lmpc(native, tmp_path: Path) -> None:
    """dlc_smoke's recorded samples through both: the same commands (to rounding), and
    not the nominal bicycle's (the file is used)."""
    from studies.bench import record_samples

    bicycle = fitted_bicycle(tmp_path)
    samples, _, _ = record_samples(scenario_name="dlc_smoke", driver="lmpc")
    path = ReferencePath.from_csv(ROOT / "hil" / "paths" / "dlc.csv")
    makers = {"python": lambda: create_controller("lmpc", model_path=bicycle),
              "c": lambda: native.NativeController("lmpc", native.data_file_for_model(bicycle, tmp_path)),
              "nominal": lambda: native.NativeController("lmpc")}
    steers = {}
    for name, make in makers.items():   # one C core per process: each C run loads it anew
        controller = make()
        controller.set_path(path)
        steers[name] = np.array([controller.step(s)[0].steer_angle for s in samples])
    difference = float(np.max(np.abs(steers["c"] - steers["python"])))
    from_nominal = float(np.max(np.abs(steers["c"] - steers["nominal"])))
    print(f"{len(samples)} steps: max |C - Python| {difference:.2e} rad, |fitted - nominal| up to {from_nominal:.2e} rad")
    assert difference < 1e-9
    assert from_nominal > 1e-3


def check_rule(figures: dict[str, float]) -> None:
    """The equivalence rule (issue 18) on `compare_runs`'s figures."""
    assert figures["frames"] > 100 and figures["largest_lsb"] <= 1
    assert figures["differing"] <= 0.01 * figures["frames"]
    assert abs(figures["rmse_python"] - figures["rmse_native"]) <= 0.001


@pytest.mark.parametrize("how", ["hil run --ecu c", "--native"])
def test_a_run_with_the_c_lmpc_and_a_fitted_bicycle_equals_the_python_ecus(native, how: str, tmp_path: Path) -> None:
    """``hil run --ecu c --model BICYCLE.json`` (the executable gets the bicycle's data
    file) and ``--native --model`` (libecu.so in the Python ECU) with LMPC on dlc_smoke:
    the Python ECU's frames with the same ``--model``, by the equivalence rule; and not
    the nominal bicycle's frames."""
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    bicycle = fitted_bicycle(tmp_path)
    scenario = load_scenario("dlc_smoke")
    python_run = run_hil(scenario, default_options("lmpc", model=bicycle))
    if how == "--native":
        c_options = default_options("lmpc", controller_factory=native.native_controller_factory("lmpc", bicycle))
    else:
        c_options = default_options("lmpc", model=bicycle, ecu="c")
    figures = compare_runs(python_run, run_hil(scenario, c_options))
    print(f"{how} --model {bicycle.name}: {figures}")
    check_rule(figures)
    nominal = compare_runs(python_run, run_hil(scenario, default_options("lmpc")))
    assert nominal["largest_lsb"] > 1   # the bicycle changed the run


def test_native_model_takes_a_fitted_bicycle_for_lmpc(native, tmp_path: Path) -> None:
    from firmware_sim.native import native_controller_factory

    controller = native_controller_factory("lmpc", fitted_bicycle(tmp_path))("lmpc")
    assert controller.name == "lmpc" and controller.data.name.startswith("bicycle-")


def ecu_data(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "firmware/tools/ecu_data.py", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=False)


def test_ecu_data_writes_the_fitted_bicycle_and_refuses_a_bad_one(native, tmp_path: Path) -> None:
    """The "bicycle" record holds the file's six fields; a field that is not a positive
    number is one error line naming the file and the field."""
    sys.path.insert(0, str(ROOT / "firmware" / "tools"))
    try:
        import ecu_data as tool
    finally:
        sys.path.pop(0)
    bicycle = fitted_bicycle(tmp_path)
    params = tool.bicycle_params(bicycle)
    nominal = nominal_model_params()
    assert params == dataclasses.replace(nominal, **{n: getattr(params, n) for n in BICYCLE_FIELDS})
    assert params.cornering_stiffness_front == pytest.approx(0.7 * nominal.cornering_stiffness_front)
    assert ecu_data("--bicycle", str(bicycle), "--out", str(tmp_path / "ok.bin")).returncode == 0
    bad = fitted_bicycle(tmp_path, yaw_inertia=-1.0)
    result = ecu_data("--bicycle", str(bad), "--out", str(tmp_path / "bad.bin"))
    assert result.returncode == 2 and not (tmp_path / "bad.bin").exists()
    assert result.stderr.strip() == f"error: {bad}: field yaw_inertia must be a positive number, got -1.0"


@pytest.mark.parametrize("controller, model, message", [
    ("eso-dkmpc", "bicycle", "error: --model {model}: a fitted bicycle file, not a Koopman artefact; eso-dkmpc "
                             "takes a Koopman artefact (PATH.npz + PATH.json, given as PATH: e.g. DIR/koopman of "
                             "python -m models.koopman_train)"),
    ("lmpc", "models/artifacts/dk_d5.json", "error: --model {model}: a Koopman artefact, not a fitted bicycle "
                                            "file; lmpc takes a fitted bicycle file (JSON: e.g. DIR/bicycle.json "
                                            "of python -m models.koopman_train --logs)"),
])
def test_hil_run_refuses_the_other_kind_of_model_file(native, controller: str, model: str, message: str,
                                                      tmp_path: Path, capsys) -> None:
    from hil.__main__ import main

    model = str(fitted_bicycle(tmp_path)) if model == "bicycle" else model
    assert main(["run", "--scenario", "dlc_smoke", "--controller", controller, "--ecu", "c", "--model", model]) != 0
    expected = message.format(model=model, npz=Path(model).with_suffix(".npz"))
    assert capsys.readouterr().err.strip().splitlines()[-1] == expected   # the Python ECU's checks


def test_the_executable_names_the_conversion_of_a_bicycle_file(native) -> None:
    result = subprocess.run([str(ROOT / "build" / "firmware" / "ecu"), "--controller", "lmpc", "--path",
                             "1=hil/paths/dlc.csv", "--model", "fit/bicycle.json", "--lockstep"], cwd=ROOT,
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "error: --model fit/bicycle.json: the C ECU reads the data file of a model, not its artefact: write it "
        "with 'python firmware/tools/ecu_data.py --bicycle fit/bicycle.json --out FILE.bin' (a fitted bicycle; "
        "--model for a Koopman artefact), then give --model FILE.bin (hil run --ecu c --model does this)")

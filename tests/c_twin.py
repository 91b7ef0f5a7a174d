"""The C core stepped beside the Python controller (`Twin`, `assert_twin_steps_equal`,
`run_twin_on_dlc_smoke`), and C cores built for test artefacts of other model forms.

Shapes are compile-time, so a test of another form builds its own firmware (``make
firmware FW_DIR=build/firmware-<form> FW_MODEL=...``, a no-op when up to date;
``build/firmware`` is not touched), loads its ``libecu.so`` (`native_on`) and runs the
twin through dlc_smoke, as tests/test_firmware_c_core.py does with the default build.
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np
import pytest

from controller.base import Command, Controller, StepDebug, VehicleSample
from controller.reference import ReferencePath

if TYPE_CHECKING:  # imported when a twin runs, not at collection
    from types import ModuleType

    from studies.closed_loop import ClosedLoopResult

ROOT = Path(__file__).resolve().parent.parent

_MISSING_TOOLS = [tool for tool in ("gcc", "cmake") if shutil.which(tool) is None]
#: A test module's ``pytestmark``: without gcc and cmake no firmware can be built.
requires_c_toolchain = pytest.mark.skipif(
    bool(_MISSING_TOOLS), reason=f"no {' or '.join(_MISSING_TOOLS)}: the C core cannot be built here "
    "(make firmware-deps installs gcc and cmake as root)")

#: Steps of dlc_smoke whose sample gets a NaN: the core's fallback, and its observer's
#: restart on the first valid sample after them (step 42).
INVALID_STEPS = frozenset({40, 41, 90})


class Twin(Controller):
    """Steps the Python controller and the C core on the same sample; drives with Python's
    command. ``invalid_steps``: step indices whose sample is replaced by one with NaN."""

    def __init__(self, python: Controller, c_core: Controller, invalid_steps: frozenset[int] = frozenset()):
        self.python, self.c_core, self.invalid = python, c_core, invalid_steps
        self.name = python.name
        self.pairs: list[tuple[Command, StepDebug, Command, StepDebug]] = []

    def set_path(self, path: ReferencePath) -> None:
        self.python.set_path(path)
        self.c_core.set_path(path)

    def reset(self) -> None:
        self.python.reset()
        self.c_core.reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        if len(self.pairs) in self.invalid:
            values = sample.measurement_values()
            values["vy"] = math.nan
            sample = VehicleSample(**values, target_speed=sample.target_speed)
        command, debug = self.python.step(sample)
        c_command, c_debug = self.c_core.step(sample)
        self.pairs.append((command, debug, c_command, c_debug))
        return command, debug


def assert_twin_steps_equal(name: str, twin: Twin) -> None:
    """Every step of ``twin``: the same commands to 1e-9 rad and 1e-6 N m, status,
    fallback, observer restart, QP iterations, predictions and cost."""
    assert len(twin.pairs) >= 150
    steer_error = max(abs(p.steer_angle - c.steer_angle) for p, _, c, _ in twin.pairs)
    torque_error = max(abs(p.drive_torque - c.drive_torque) for p, _, c, _ in twin.pairs)
    print(f"{name}: {len(twin.pairs)} steps, max |steer difference| {steer_error:.2e} rad, "
          f"torque {torque_error:.2e} N m")
    assert steer_error < 1e-9 and torque_error < 1e-6
    for i, (_, debug, _, c_debug) in enumerate(twin.pairs):
        assert (c_debug.status, c_debug.fallback, c_debug.observer_reset, c_debug.iterations) == \
            (debug.status, debug.fallback, debug.observer_reset, debug.iterations), f"step {i}"
        assert c_debug.predicted_state.shape == debug.predicted_state.shape
        if debug.predicted_state.size:
            assert np.allclose(c_debug.predicted_state, debug.predicted_state, atol=1e-7)
            assert np.allclose(c_debug.predicted_pose, debug.predicted_pose, atol=1e-7)
            assert c_debug.cost == pytest.approx(debug.cost, rel=1e-7, abs=1e-9)


def replace_unless_same(staging: Path, path: Path) -> None:
    """Move the artefact ``staging`` (.npz + .json) to ``path``, or drop it where ``path``
    holds the same content already (np.savez stamps the time: a rewrite would rebuild the
    firmware built for ``path`` every run)."""
    same = path.with_suffix(".npz").is_file() and path.with_suffix(".json").is_file()
    if same:
        with np.load(staging.with_suffix(".npz")) as new, np.load(path.with_suffix(".npz")) as old:
            same = sorted(new.files) == sorted(old.files) and all(np.array_equal(new[k], old[k]) for k in new.files)
        same = same and (json.loads(staging.with_suffix(".json").read_text())
                         == json.loads(path.with_suffix(".json").read_text()))
    for suffix in (".npz", ".json"):
        if same:
            staging.with_suffix(suffix).unlink()
        else:
            staging.with_suffix(suffix).replace(path.with_suffix(suffix))


def build_firmware(build: Path, model: Path) -> None:
    """``make firmware`` into ``build`` for the artefact ``model`` (both under ROOT; a no-op
    when up to date)."""
    done = subprocess.run(["make", "-s", "--no-print-directory", "firmware", f"FW_DIR={build.relative_to(ROOT)}",
                           f"FW_MODEL={model.relative_to(ROOT)}"], cwd=ROOT, capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stdout + done.stderr


def firmware_for(model: Path, write_artefact: Callable[[Path], object]) -> Path:
    """The firmware for the test artefact ``model`` (without .npz/.json), built into its
    folder and up to date: ``write_artefact(model)`` writes the artefact (leaving it as it
    is when its content is the same, `replace_unless_same`), then `build_firmware`.
    Returns the build folder (a module-scoped fixture's body)."""
    build = model.parent
    build.mkdir(parents=True, exist_ok=True)
    write_artefact(model)
    build_firmware(build, model)
    return build


def native_on(library: Path) -> Iterator[ModuleType]:
    """firmware_sim.native on ``library`` while the generator runs (a fixture's body). The
    module loads one library per process: the default build's (if another test loaded it)
    is set aside and put back afterwards (the libraries' static cores are separate)."""
    from firmware_sim import native as module

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(module, "_library", None)
        module.load_library(library)
        yield module


def run_twin_on_dlc_smoke(name: str, python: Controller, c_core: Controller) -> tuple[Twin, ClosedLoopResult]:
    """Step ``python`` and ``c_core`` as a `Twin` through the closed loop of dlc_smoke (160
    steps, :data:`INVALID_STEPS` with a NaN sample; Python's command drives the plant) and
    assert every step equal (`assert_twin_steps_equal`: commands to 1e-9 rad, status,
    iterations, predictions and cost). Returns the twin (its ``pairs``, one per step) and
    the closed-loop run."""
    from hil.scenario import load_scenario
    from studies.closed_loop import run_closed_loop

    twin = Twin(python, c_core, INVALID_STEPS)
    result = run_closed_loop(load_scenario("dlc_smoke"), twin)
    assert result.completed, result.failure
    assert_twin_steps_equal(name, twin)
    return twin, result

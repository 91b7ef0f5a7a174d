"""C cores built for test artefacts of other model forms, stepped beside the Python
controller: the helpers of tests/test_firmware_c_bilinear.py and
tests/test_firmware_c_edmdc.py.

Shapes are compile-time, so each such test builds its own firmware (``make firmware
FW_DIR=build/firmware-<form> FW_MODEL=...``, a no-op when up to date; ``build/firmware``
is not touched), loads its ``libecu.so`` and runs the twin of
tests/test_firmware_c_core.py (`Twin`, `assert_twin_steps_equal`) through dlc_smoke.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np
import pytest

from controller.base import Controller
from test_firmware_c_core import Twin, assert_twin_steps_equal

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

"""``make firmware FW_MODEL=...`` builds for the model it is given, whatever the file dates
(mk/firmware.mk's ``$(FW_DIR)/model_choice``): another model whose files are older than an
existing build regenerates its sources and data file, and the same choice again rebuilds
nothing. Only the two rules that read the model run (the generated sources' stamp and the
data file, a few seconds; nothing is compiled), into ``build/firmware-model-choice``."""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "build" / "firmware-model-choice"
COMMITTED = ROOT / "models" / "artifacts" / "dk_d5"


def make_for(model: Path) -> None:
    """The generated sources' stamp and the data file of BUILD for ``model`` (without
    .npz/.json, under ROOT)."""
    folder = BUILD.relative_to(ROOT)
    done = subprocess.run(["make", "-s", "--no-print-directory", "-o", ".venv/.installed", f"FW_DIR={folder}",
                           f"FW_MODEL={model.relative_to(ROOT)}", f"{folder}/gen/stamp", f"{folder}/ecu_data.bin"],
                          cwd=ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout + done.stderr


def mtimes() -> tuple[int, int]:
    return (BUILD / "gen" / "stamp").stat().st_mtime_ns, (BUILD / "ecu_data.bin").stat().st_mtime_ns


def test_another_model_older_than_the_build_is_built_for() -> None:
    shutil.rmtree(BUILD, ignore_errors=True)
    BUILD.mkdir(parents=True)
    first, other = BUILD / "first", BUILD / "other"
    for suffix in (".npz", ".json"):
        shutil.copyfile(COMMITTED.with_suffix(suffix), first.with_suffix(suffix))
    with np.load(COMMITTED.with_suffix(".npz")) as arrays:  # the same shapes, other offsets
        values = {name: arrays[name] for name in arrays.files}
    values["affine_n"] = values["affine_n"] + 1e-3
    np.savez(other.with_suffix(".npz"), **values)
    shutil.copyfile(COMMITTED.with_suffix(".json"), other.with_suffix(".json"))
    an_hour_ago = (BUILD.stat().st_mtime - 3600.0,) * 2
    for suffix in (".npz", ".json"):  # "other" was trained before the build below
        os.utime(other.with_suffix(suffix), an_hour_ago)

    make_for(first)
    first_data = (BUILD / "ecu_data.bin").read_bytes()
    make_for(other)
    version = (BUILD / "gen" / "ecu_version.c").read_text()
    assert f"{other.relative_to(ROOT)}.npz" in version and f"{first.relative_to(ROOT)}.npz" not in version
    assert (BUILD / "ecu_data.bin").read_bytes() != first_data
    assert (BUILD / "model_choice").read_text().startswith(f"FW_MODEL {other.relative_to(ROOT)}\n")
    built = mtimes()
    make_for(other)  # the same choice: nothing rebuilt
    assert mtimes() == built
    make_for(first)  # and back, although "first" is older than the build now too
    assert (BUILD / "ecu_data.bin").read_bytes() == first_data

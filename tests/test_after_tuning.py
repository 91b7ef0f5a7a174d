"""`make after-tuning` (mk/after_tuning.mk): its list holds every study that the tuning file
feeds, as results/PROVENANCE.json records their inputs, and refuses an unknown start."""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

from studies.provenance import load_manifest

ROOT = Path(__file__).resolve().parent.parent
TUNING_FILE = "controller/tuning.toml"
#: Stamped commands with the tuning file among their inputs that are tuning stages
#: themselves (they write the file), not studies after it.
TUNING_STAGES = {"tune", "tune-observer", "tune-observer-refine", "tune-slip-target", "grip-envelope"}


def _targets(variable: str = "AFTER_TUNING_TARGETS") -> list[str]:
    text = (ROOT / "mk" / "after_tuning.mk").read_text()
    found = re.search(rf"^{variable} := (.*?)(?<!\\)$", text, re.M | re.S)
    assert found, f"mk/after_tuning.mk has no {variable}"
    return found.group(1).replace("\\\n", " ").split()


def _make_list(variable: str) -> list[str]:
    """``variable`` as make expands it."""
    result = subprocess.run(["make", "--no-print-directory", "-s", "-f", "mk/after_tuning.mk", "-f", "-",
                             "show"], input=f"show:\n\t@echo $({variable})\n", cwd=ROOT, capture_output=True,
                            text=True, check=True)
    return result.stdout.split()


def test_every_study_the_tuning_file_feeds_is_in_the_list() -> None:
    targets = _targets()
    fed = set()
    for name, entry in load_manifest(ROOT).items():
        if TUNING_FILE in entry.get("inputs", []):
            fed.add(entry["command"].split()[1])
    missing = sorted(fed - set(targets) - TUNING_STAGES)
    assert not missing, f"studies fed by {TUNING_FILE} missing from AFTER_TUNING_TARGETS: {missing}"
    assert len(targets) == len(set(targets))
    # the machine's measurements last, each study after the files it reads
    assert targets[-2:] == ["bench", "timing"]
    assert targets.index("identify") < targets.index("identify-lsq")
    assert targets.index("faults") < targets.index("faults-c")
    assert targets.index("seed-spread-models") < targets.index("seed-spread")
    assert targets[0] == "firmware"


def test_an_unknown_start_is_refused() -> None:
    result = subprocess.run(["make", "--no-print-directory", "-s", "after-tuning", "AFTER_TUNING_FROM=nonsense"],
                            cwd=ROOT, capture_output=True, text=True)
    assert result.returncode != 0
    assert "AFTER_TUNING_FROM=nonsense is not one of" in result.stderr


def test_the_retune_runs_every_tuning_stage_in_order_then_every_study_after_it() -> None:
    stages = _targets("RETUNE_STAGES")
    assert set(stages) == TUNING_STAGES
    # each stage takes the ones before it as given (docs/tuning.md): weights, observers, grip
    assert stages == ["tune", "tune-observer", "tune-observer-refine", "tune-slip-target", "grip-envelope"]
    assert _make_list("RETUNE_TARGETS") == stages + _targets()


def test_an_unknown_retune_start_is_refused() -> None:
    result = subprocess.run(["make", "--no-print-directory", "-s", "retune", "RETUNE_FROM=nonsense"],
                            cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 2
    assert "RETUNE_FROM=nonsense is not one of: tune tune-observer" in result.stderr

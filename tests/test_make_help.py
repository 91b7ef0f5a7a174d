"""`make help` lists every target of Makefile and mk/*.mk, each with one help line.

The targets come from make's own database (``make -pRrq``), not from the awk program of
``make help``, so a target added without a ``## `` comment (on its line or the line above)
fails here. Add the comment; the line is what ``make help`` prints.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NO_HELP = "(no help line)"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def _make(directory: Path, *args: str) -> str:
    env = {key: value for key, value in os.environ.items() if key not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    result = subprocess.run(["make", "--no-print-directory", "-C", str(directory), *args],
                            capture_output=True, text=True, env=env, timeout=60)
    return result.stdout


def database_targets(directory: Path) -> set[str]:
    """Explicit targets of the makefiles in ``directory``, from make's database.

    File targets (a path with '/', such as ``.venv/.installed``), special targets
    (``.PHONY``) and the makefiles themselves are left out: they are not commands.
    """
    database = _make(directory, "-pRrq", ":")
    files = database.split("# Files", 1)[1].split("# Finished Make data base", 1)[0]
    targets = set()
    for block in files.split("\n\n"):
        lines = [line for line in block.strip("\n").splitlines() if line]
        if not lines or lines[0].startswith("# Not a target"):
            continue
        rule = next((line for line in lines if not line.startswith("#")), "")
        found = re.match(r"^([^\s:#=]+):(?!=)", rule)
        if not found:
            continue
        name = found.group(1)
        if name.startswith(".") or "/" in name or name == "Makefile" or name.endswith(".mk"):
            continue
        targets.add(name)
    return targets


def help_lines(directory: Path) -> dict[str, str]:
    """``make help``'s lines ``make TARGET  text`` as {target: text}."""
    lines = {}
    for line in _make(directory, "help").splitlines():
        found = re.match(r"^\s+make (\S+)\s+(.*)$", line)
        if found:
            assert found.group(1) not in lines, f"make help lists {found.group(1)} twice"
            lines[found.group(1)] = found.group(2).strip()
    return lines


def test_every_target_has_one_help_line() -> None:
    targets = database_targets(ROOT)
    lines = help_lines(ROOT)
    print(f"{len(targets)} targets; make help lists {len(lines)}")
    assert len(targets) > 30
    missing = sorted(name for name in targets if lines.get(name, NO_HELP) == NO_HELP)
    assert not missing, ("targets without a help line (add a '## text' comment on the target's "
                         f"line or just above it): {missing}")
    assert set(lines) == targets, f"make help lists non-targets: {sorted(set(lines) - targets)}"


def test_the_documented_everyday_targets_are_there() -> None:
    lines = help_lines(ROOT)
    for name in ("test", "test-fast", "run", "help", "readme", "contract-tables"):
        assert name in lines and lines[name] != NO_HELP


def test_a_new_target_without_a_help_line_is_caught(tmp_path: Path) -> None:
    shutil.copy(ROOT / "Makefile", tmp_path / "Makefile")
    shutil.copytree(ROOT / "mk", tmp_path / "mk")
    (tmp_path / "mk" / "zz_new.mk").write_text(
        ".PHONY: documented undocumented\n"
        "## a documented target\ndocumented:\n\t@true\n\n"
        "undocumented: ## on the target line\n\t@true\n\n"
        "# an ordinary comment is not a help line\nforgotten:\n\t@true\n")
    lines = help_lines(tmp_path)
    assert lines["documented"] == "a documented target"
    assert lines["undocumented"] == "on the target line"
    assert lines["forgotten"] == NO_HELP
    assert {"documented", "undocumented", "forgotten"} <= database_targets(tmp_path)

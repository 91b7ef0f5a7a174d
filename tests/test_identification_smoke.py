"""docs/identification.md's quick check (issue 39 items 3 and 4): its commands as written.

The block's first lines (the folder and the copied drive) run here, into a temporary
folder; the copy must load, with the shipped path file found from the repository. The
drive, the training and the runs are only parsed (their options must exist): they take
tens of seconds; the whole workflow runs in ``make identify``'s study.
"""
from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

from hil.scenario import SCENARIO_DIR, load_scenario

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "identification.md"
SMOKE_FOLDER = "build/id-smoke"


def _blocks() -> list[str]:
    return re.findall(r"```sh\n(.*?)```", DOC.read_text(), flags=re.S)


def _commands(block: str) -> list[str]:
    """The block's commands, continuation lines joined, comments dropped."""
    joined = block.replace("\\\n", " ")
    return [line.split("  #")[0].strip() for line in joined.splitlines() if line.strip()]


def _smoke_commands() -> list[str]:
    blocks = [b for b in _blocks() if SMOKE_FOLDER in b]
    assert len(blocks) == 1, "docs/identification.md: one sh block of the quick check"
    return _commands(blocks[0])


def test_every_command_of_the_page_creates_its_folder_first() -> None:
    """A ``--log`` into ``build/...`` comes after the ``mkdir -p`` of its folder."""
    for block in _blocks():
        made: set[str] = set()
        for command in _commands(block):
            words = shlex.split(command)
            if words[:2] == ["mkdir", "-p"]:
                made.update(words[2:])
            if "--log" in words:
                folder = str(Path(words[words.index("--log") + 1]).parent)
                assert folder in made, f"{command}: no mkdir -p {folder} before it"


def test_the_quick_check_writes_a_drive_that_loads(tmp_path: Path) -> None:
    commands = _smoke_commands()
    assert commands[0] == f"mkdir -p {SMOKE_FOLDER}" and commands[1].startswith("sed ")
    folder = tmp_path / "id-smoke"
    for command in commands[:2]:
        subprocess.run(["bash", "-c", command.replace(SMOKE_FOLDER, str(folder))], cwd=REPO,
                       check=True)
    drive = load_scenario(folder / "drive.toml")
    shipped = load_scenario(SCENARIO_DIR / "identification" / "drive.toml")
    print(f"{drive.duration_s} s drive on {drive.path_file}")
    assert drive.duration_s == 90.0 and drive.path_file == shipped.path_file
    assert drive.speed_profile == shipped.speed_profile


def test_the_quick_checks_commands_parse() -> None:
    from hil.__main__ import build_parser as hil_parser
    from models.koopman_cli import build_parser as train_parser

    parsed = []
    for command in _smoke_commands()[2:]:
        words = shlex.split(command)
        assert words[:2] == ["python", "-m"], command
        if words[2] == "hil":
            args = hil_parser()[0].parse_args(words[3:])
        else:
            assert words[2] == "models.koopman_train", command
            args = train_parser().parse_args(words[3:])
        parsed.append(args)
    assert [getattr(a, "subcommand", "train") for a in parsed] == ["run", "train", "run", "run"]
    assert parsed[1].epochs == 3 and parsed[0].excite == "prbs-torque"

"""Every command written in README.md and docs/*.md names something that exists: a make
target of the Makefile (and the make variables it sets), a Python module, and options that
the module's (sub)command accepts, as its ``--help`` lists them. ``eso-hil`` and ``eso-ecu``
are the console scripts of ``python -m hil`` and ``python -m firmware_sim``.

The commands are taken from code blocks (fenced or indented) and inline code spans; a
trailing comment and backslash continuations are handled. A command whose run takes minutes
is only checked, not run: this test catches the renamed option, the removed target and the
misspelt module that a newcomer would meet first. The quick ones also run, as written, in
``tests/test_doc_commands_run.py``.
"""
from __future__ import annotations

import functools
import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: Console scripts -> the module they run.
SCRIPTS = {"eso-hil": "hil", "eso-ecu": "firmware_sim"}
#: Modules of other projects: only their presence is checked.
THIRD_PARTY = ("pytest", "can", "cantools", "pip", "venv", "ray", "osqp", "http")
_PYTHON = re.compile(r"^python3?$")


def _candidate_lines(text: str) -> list[str]:
    """Code lines of a Markdown text: fenced blocks, indented blocks and inline spans."""
    lines: list[str] = []
    fenced = False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or line.startswith("    "):
            lines.append(line.strip())
        else:
            lines += re.findall(r"`([^`]+)`", line)
    joined: list[str] = []
    for line in lines:  # backslash continuations
        if joined and joined[-1].endswith("\\"):
            joined[-1] = joined[-1][:-1] + " " + line
        else:
            joined.append(line)
    return joined


def _command(line: str) -> list[str] | None:
    """The words of a make / python -m / console-script command, or None."""
    line = line.strip().removeprefix("$ ")
    line = re.split(r"\s+#\s", line, maxsplit=1)[0]
    for separator in ("&&", "|", ";"):
        line = line.split(separator)[0]
    try:
        words = shlex.split(line)
    except ValueError:
        return None
    while words and re.fullmatch(r"[A-Z_]+=\S*", words[0]):  # leading environment settings
        words = words[1:]
    if not words:
        return None
    words[0] = words[0].removeprefix(".venv/bin/")
    if words[0] == "make" or words[0] in SCRIPTS:
        return words
    if _PYTHON.match(words[0]) and len(words) >= 3 and words[1] == "-m":
        return words
    return None


def documented_commands() -> list[tuple[str, list[str]]]:
    """(document name, words) of every command in the manuals and the README."""
    found = []
    for document in DOCUMENTS:
        for line in _candidate_lines(document.read_text(encoding="utf-8")):
            words = _command(line)
            if words is not None:
                found.append((document.name, words))
    return found


@functools.cache
def make_targets() -> frozenset[str]:
    """Every target make knows (its database, without running a recipe)."""
    database = subprocess.run(["make", "-qp", "-f", "Makefile", ".DEFAULT_GOAL_DOES_NOT_EXIST"], cwd=ROOT,
                              capture_output=True, text=True).stdout
    return frozenset(m.group(1) for m in re.finditer(r"^([A-Za-z0-9][A-Za-z0-9_.-]*):(?!=)", database, re.M))


@functools.cache
def make_text() -> str:
    return "\n".join(path.read_text(encoding="utf-8") for path in [ROOT / "Makefile", *sorted((ROOT / "mk").glob("*.mk"))])


@functools.cache
def help_text(module: str, subcommands: tuple[str, ...]) -> str:
    """``python -m module [subcommands] --help`` (stdout and stderr)."""
    done = subprocess.run([sys.executable, "-m", module, *subcommands, "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    return done.stdout + done.stderr


def _subcommands(module: str, arguments: list[str]) -> tuple[str, ...]:
    """The leading words of ``arguments`` that the module's help lists as subcommands."""
    chosen: list[str] = []
    for word in arguments:
        if not re.fullmatch(r"[a-z][a-z0-9-]*", word):
            break
        listing = help_text(module, tuple(chosen))
        choice = r"\{[^}]*\b" + re.escape(word) + r"\b[^}]*\}"  # {run,replay} or a listed SUBCOMMAND
        if not (re.search(choice, listing) or re.search(r"^ {2,}" + re.escape(word) + r"(?: |$)", listing, re.M)):
            break
        chosen.append(word)
    return tuple(chosen)


def problems_of(words: list[str]) -> list[str]:
    """What does not exist in one command (empty when all of it does)."""
    if words[0] == "make":
        problems = []
        for word in words[1:]:
            if word.startswith("-"):
                continue
            setting = re.fullmatch(r"([A-Z_][A-Z0-9_]*)=.*", word)
            if setting:
                if not re.search(r"\b" + setting.group(1) + r"\b", make_text()):
                    problems.append(f"make variable {setting.group(1)} is used nowhere in the Makefile")
            elif "/" in word:  # a file target (a pattern rule's): its variables are checked above
                continue
            elif word not in make_targets():
                problems.append(f"make target {word!r} does not exist")
        return problems
    if words[0] in SCRIPTS:
        module, arguments = SCRIPTS[words[0]], words[1:]
    else:
        module, arguments = words[2], words[3:]
    if module == "...":  # "python -m ..." stands for any module
        return []
    if not re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", module):
        return [f"{module!r} is not a module name"]
    if "--" in arguments:  # a wrapper (python -m hil.vcan -- COMMAND): its options, then the command's
        inner = _command(shlex.join(arguments[arguments.index("--") + 1:]))
        outer = [*words[:len(words) - len(arguments)], *arguments[:arguments.index("--")]]
        return problems_of(outer) + (problems_of(inner) if inner is not None else [])
    if importlib.util.find_spec(module.split(".")[0]) is None:
        return [f"module {module} is not installed"]
    if module.split(".")[0] in THIRD_PARTY:
        return [] if importlib.util.find_spec(module) is not None else [f"module {module} does not exist"]
    if importlib.util.find_spec(module) is None:
        return [f"module {module} does not exist"]
    subcommands = _subcommands(module, arguments)
    listing = help_text(module, subcommands)
    options = {word.split("=")[0] for word in arguments if re.fullmatch(r"--[a-z][a-z0-9-]*(=.*)?", word)}
    return [f"{' '.join([module, *subcommands])} has no option {option}" for option in sorted(options)
            if not re.search(re.escape(option) + r"(?![a-z0-9-])", listing)]


def test_the_extraction_finds_the_commands_people_run() -> None:
    commands = documented_commands()
    firsts = {words[0] for _, words in commands}
    assert {"make", "eso-hil"} <= firsts and len(commands) > 100
    assert _command("make tune TUNE_ARGS='--controllers lmpc'   # only LMPC") == \
        ["make", "tune", "TUNE_ARGS=--controllers lmpc"]
    assert _command("CI=true .venv/bin/python -m hil run --scenario x && echo") == \
        ["python", "-m", "hil", "run", "--scenario", "x"]
    assert _command("cd build") is None


def test_a_wrong_target_module_or_option_is_named() -> None:
    assert problems_of(["make", "no-such-target"]) == ["make target 'no-such-target' does not exist"]
    assert problems_of(["python", "-m", "studies.no_such_module"]) == ["module studies.no_such_module does not exist"]
    assert problems_of(["eso-hil", "run", "--scenario", "dlc_high_mu", "--no-such-option"]) == \
        ["hil run has no option --no-such-option"]


@pytest.mark.slow
def test_every_documented_command_names_what_exists() -> None:
    failures = []
    for document, words in documented_commands():
        failures += [f"{document}: `{' '.join(words)}`: {problem}" for problem in problems_of(words)]
    print(f"{len(documented_commands())} commands checked")
    assert not failures, "\n".join(failures)

"""The quick commands of README.md and docs/*.md run as written: exit status 0 and no Python
traceback. The commands are those of ``test_doc_commands`` (same extraction); the others
stay checked there, for the existence of what they name.

Which commands are quick is decided by :func:`classify`, a short rule, not by a list of
lines:

* a command with a placeholder (``FILE``, ``DIR``, ``REV``, ``NAME``: a word in capitals
  that is not a ``VAR=`` setting; ``...``; an optional ``[--flag]``; ``<name>``) cannot
  run as written;
* ``--help`` only prints (argparse exits before any work);
* ``make help`` is the one make target run: every other one builds, installs (apt-get as
  root), runs the test suite or a study;
* ``eso-hil run``, ``faults`` (one run), ``decode`` and ``replay`` (``python -m hil``) run
  when every file they read is committed (a fresh clone has it: ``results/logs/`` is made
  by ``make run``), every file they write is a bare name (it lands in the scratch folder
  the commands run in), and, for a drive, it is short: lockstep on the virtual bus, the
  Python ECU (the C one is built by ``make firmware``), at most ``QUICK_DRIVE_S`` seconds
  of driving and a controller other than ``nmpc``. Measured on 2 cores: dlc_high_mu
  (13.5 s of driving) runs in ~4 s with lmpc-eso or eso-dkmpc, in ~13 s with nmpc.

Everything else is long. The commands run in a fresh clone of the working tree (a copy of
its files in a repository of its own), so they see only committed inputs and what they
write shows in the clone's ``git status``: it must hold nothing but the bare output names
the commands give (others working in the checkout meanwhile cannot upset the check).
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import io
import os
import re
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from test_doc_commands import ROOT, SCRIPTS, documented_commands

#: Category of a command that runs here; the others are only checked for existence.
QUICK = "quick"
#: Longest drive (scenario seconds) of an ``eso-hil run`` that counts as quick.
QUICK_DRIVE_S = 15.0
#: Controllers that solve a nonlinear program each step: about real time on 2 cores.
SLOW_CONTROLLERS = frozenset({"nmpc"})
#: Seconds a quick command may take before it is reported as not quick after all.
TIMEOUT_S = 60.0
#: A word in capitals (not a ``VAR=`` setting, no underscore: CAN names are not
#: placeholders) or ``...``, ``[optional]``, ``<name>``.
_PLACEHOLDER = re.compile(r"(?<![A-Za-z0-9_])[A-Z]+(?![A-Za-z0-9_=])|\.\.\.|^\[|\]$|^<")
_TRACEBACK = "Traceback (most recent call last)"


def placeholder(words: list[str]) -> str | None:
    """The first word of ``words`` that the reader must fill in, or None."""
    return next((word for word in words[1:] if _PLACEHOLDER.search(word)), None)


@functools.cache
def tree_files() -> frozenset[str]:
    """Paths, relative to the checkout, of the files a clone of the working tree would have:
    tracked or new (not ignored), without the deleted ones."""
    listing = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                             capture_output=True, text=True, check=True)
    return frozenset(name for name in listing.stdout.split("\0") if name and (ROOT / name).is_file())


def _in_clone(path: str | Path) -> bool:
    """Whether ``path`` (a file, a folder or an artefact's stem such as
    ``models/artifacts/dk_d5``) is in a clone of the working tree."""
    name = os.path.normpath(path)
    return any(file == name or file.startswith((f"{name}/", f"{name}.")) for file in tree_files())


def _hil_arguments(arguments: list[str]) -> argparse.Namespace | None:
    """``eso-hil``'s parse of ``arguments``, or None where it lacks a required one (a
    subcommand named in prose)."""
    before = dict(os.environ)
    from hil.__main__ import build_parser  # sets BLAS thread counts: meant for its own process

    os.environ.clear()
    os.environ.update(before)
    parser, _ = build_parser()
    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            return parser.parse_args(arguments)
    except SystemExit:
        return None


def _hil_files(args: argparse.Namespace) -> tuple[list[Path], list[Path]]:
    """(files read, files written) of an ``eso-hil run | decode | replay``."""
    paths = [Path(spec.split("=", 1)[-1]) for spec in getattr(args, "path", [])]
    if args.subcommand in ("run", "faults"):
        scenario = Path(args.scenario)
        shipped = scenario.suffix != ".toml" and "/" not in args.scenario
        reads = [Path("hil/scenarios") / f"{args.scenario}.toml" if shipped else scenario, *paths]
        if args.subcommand == "faults":  # one run; its --out is the campaign's
            return reads, []
        reads += [Path(args.model)] if args.model else []
        reads += [Path("build/firmware/ecu")] if args.ecu == "c" else []
        plot = [args.plot] if args.plot not in (None, Path(".")) else []  # Path("."): --plot alone
        return reads, [Path(p) for p in (args.log, args.out) if p] + plot
    if args.subcommand == "decode":
        return [args.log, *paths, *([Path(args.dbc)] if args.dbc else [])], \
            [Path(p) for p in (args.csv, args.plot) if p]
    reads = [args.log, *paths] + [Path(p) for p in (args.ref, args.model, args.dbc) if p]
    writes = [Path(args.json)] if args.json not in (None, "-") else []
    if args.write_ref is not None:  # "" writes <log>.ref.log next to the log
        writes.append(Path(args.write_ref) if args.write_ref else Path(f"{args.log}.ref.log"))
    return reads, writes


def _classify_hil(arguments: list[str]) -> str:
    """Category of an ``eso-hil`` command (see the module's docstring)."""
    if _asks_help(arguments):
        return QUICK
    args = _hil_arguments(arguments)
    if args is None:
        return "named in prose (a required argument is not written)"
    if args.subcommand not in ("run", "faults", "decode", "replay") or getattr(args, "campaign", False):
        return "long"
    reads, writes = _hil_files(args)
    if not all(_in_clone(path) for path in reads):
        return "reads a file another command makes"
    if any(path.parent != Path(".") for path in writes):
        return "writes outside the folder it runs in"
    if args.subcommand == "replay" and args.realtime:
        return "long"
    if args.subcommand in ("run", "faults") and not _short_drive(args, ROOT / reads[0]):
        return "long"
    return QUICK


def _short_drive(args: argparse.Namespace, scenario: Path) -> bool:
    """Whether an ``eso-hil run`` / ``faults`` (one run) drives at most ``QUICK_DRIVE_S``
    seconds in lockstep on the virtual bus with a controller that solves fast."""
    from hil.scenario import load_scenario

    drive_s = getattr(args, "duration", None) or load_scenario(scenario).duration_s
    return (drive_s <= QUICK_DRIVE_S and getattr(args, "lockstep", True)
            and getattr(args, "interface", None) in (None, "virtual")
            and args.controller.lower() not in SLOW_CONTROLLERS)


def _asks_help(arguments: list[str]) -> bool:
    """Whether a command asks for its help (not a wrapped command's, after ``--``)."""
    own = arguments[:arguments.index("--")] if "--" in arguments else arguments
    return "--help" in own or "-h" in own


def classify(words: list[str]) -> str:
    """``QUICK`` for a command that runs here, else why it does not."""
    if placeholder(words):
        return "placeholder"
    if words[0] == "make":
        return QUICK if words[1:] == ["help"] else "long"
    module, arguments = (SCRIPTS[words[0]], words[1:]) if words[0] in SCRIPTS else (words[2], words[3:])
    if module == "hil":
        return _classify_hil(arguments)
    return QUICK if _asks_help(arguments) else "long"


def command_line(words: list[str]) -> list[str]:
    """The argv that runs ``words`` with this environment's Python and console scripts."""
    if words[0] in SCRIPTS:
        script = Path(sys.executable).parent / words[0]
        return [str(script), *words[1:]] if script.exists() else [sys.executable, "-m", SCRIPTS[words[0]], *words[1:]]
    if words[0] == "make":
        return words
    return [sys.executable, *words[1:]]


def _environment(clone: Path) -> dict[str, str]:
    """The caller's environment, with the clone's packages first (the console scripts
    import from it, as ``python -m`` does from its working folder), without a display (a
    window would wait for a person), a CAN bus of its own or an outer make's flags."""
    dropped = ("DISPLAY", "WAYLAND_DISPLAY", "CAN_INTERFACE", "CAN_CHANNEL", "MAKEFLAGS", "MAKELEVEL", "MFLAGS")
    environment = {key: value for key, value in os.environ.items() if key not in dropped}
    python_path = os.pathsep.join(filter(None, [str(clone), environment.get("PYTHONPATH")]))
    return {**environment, "MPLBACKEND": "Agg", "PYTHONPATH": python_path}


def fresh_clone(folder: Path) -> Path:
    """``folder`` made a clone of the working tree (its files copied, ~15 MB, and committed
    to a repository of its own): the commands see what a fresh clone has, and whatever they
    write shows in its ``git status``, whatever others change in the checkout meanwhile."""
    for name in tree_files():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, folder / name)
    identity = ["-c", "user.name=docs", "-c", "user.email=docs@localhost", "-c", "commit.gpgsign=false"]
    for git in (["init", "-q"], ["add", "-A"], ["commit", "-q", "--no-verify", "-m", "working tree"]):
        subprocess.run(["git", *identity, *git], cwd=folder, capture_output=True, check=True)
    return folder


def written_files(folder: Path) -> set[str]:
    """Files added or changed in the clone at ``folder`` since its commit, ignored ones
    (build/, results/logs/) included, Python's byte-code caches left out."""
    status = subprocess.run(["git", "status", "--porcelain", "--ignored", "--untracked-files=all"], cwd=folder,
                            capture_output=True, text=True, check=True).stdout
    return {line[3:] for line in status.splitlines() if "__pycache__/" not in line}


def declared_outputs(words: list[str]) -> set[str]:
    """The files a quick command says it writes (bare names: see :func:`classify`)."""
    if SCRIPTS.get(words[0]) != "hil" and words[2:3] != ["hil"]:
        return set()
    args = _hil_arguments(words[1:] if words[0] in SCRIPTS else words[3:])
    return {str(path) for path in _hil_files(args)[1]} if args is not None else set()


def run_documented(words: list[str], folder: Path) -> tuple[str | None, float]:
    """(what went wrong or None, seconds) of one run of ``words`` in ``folder``."""
    start = time.monotonic()
    try:
        done = subprocess.run(command_line(words), cwd=folder, capture_output=True, text=True,
                              env=_environment(folder), timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return f"still running after {TIMEOUT_S:.0f} s: not quick", TIMEOUT_S
    seconds = time.monotonic() - start
    output = done.stdout + done.stderr
    if done.returncode != 0 or _TRACEBACK in output:
        return f"exit status {done.returncode}:\n{output[-1500:]}", seconds
    return None, seconds


def test_the_rule_runs_only_what_is_quick_and_writes_nowhere_else() -> None:
    assert classify(["make", "help"]) == QUICK
    assert classify(["make", "setup"]) == "long"
    assert classify(["eso-hil", "--help"]) == QUICK
    assert classify(["python", "-m", "studies.run_all", "--help"]) == QUICK
    assert classify(["python", "-m", "studies.run_all"]) == "long"
    assert classify(["make", "restamp", "BASE=REV"]) == "placeholder"
    assert classify(["make", "tune", "TUNE_ARGS=--controllers lmpc"]) == "long"
    assert classify(["eso-hil", "faults", "--scenario", "NAME", "--bus", "kind=..."]) == "placeholder"
    assert placeholder(["eso-hil", "play", "f.asc", "--ids", "VEH_DYN,PLANNER_REQ"]) is None
    run = ["eso-hil", "run", "--scenario", "dlc_smoke", "--controller", "lmpc"]
    assert classify([*run, "--plot", "view.png"]) == QUICK
    assert classify([*run, "--out", "/tmp/x"]) == "writes outside the folder it runs in"
    assert classify([*run, "--ecu", "c"]) == "reads a file another command makes"
    assert classify(["eso-hil", "run", "--scenario", "dlc_high_mu", "--controller", "nmpc"]) == "long"
    assert classify(["eso-hil", "run", "--scenario", "slalom", "--controller", "lmpc"]) == "long"
    assert classify(["eso-hil", "faults", "--scenario", "dlc_smoke", "--mu-step", "3.0:0.5"]) == QUICK
    assert classify(["eso-hil", "faults", "--campaign"]) == "long"
    assert classify(["eso-hil", "replay", "results/logs/dlc_high_mu__eso-dkmpc.log"]) == \
        "reads a file another command makes"
    log = "tests/data/logs/lockstep_lmpc.log"
    assert classify(["eso-hil", "replay", log]) == QUICK
    assert classify(["eso-hil", "replay", log, "--write-ref"]) == "writes outside the folder it runs in"
    assert classify(["eso-hil", "decode", log, "--csv", "out.csv"]) == QUICK
    assert classify(["eso-hil", "decode"]) == "named in prose (a required argument is not written)"


def test_the_clone_shows_what_a_command_writes_ignored_files_included(tmp_path: Path) -> None:
    clone = fresh_clone(tmp_path)
    assert (clone / "Makefile").read_bytes() == (ROOT / "Makefile").read_bytes() and written_files(clone) == set()
    (clone / "build").mkdir()
    (clone / "build" / "made.csv").write_text("x\n")
    (clone / "view.png").write_bytes(b"")
    (clone / "hil" / "__pycache__").mkdir(exist_ok=True)
    (clone / "hil" / "__pycache__" / "x.pyc").write_bytes(b"")
    assert written_files(clone) == {"build/made.csv", "view.png"}
    assert declared_outputs(["eso-hil", "run", "--scenario", "dlc_smoke", "--controller", "lmpc",
                             "--plot", "view.png"]) == {"view.png"}


@pytest.mark.slow
def test_every_quick_documented_command_runs_as_written(tmp_path: Path) -> None:
    documents: dict[tuple[str, ...], list[str]] = {}
    for document, words in documented_commands():
        documents.setdefault(tuple(words), []).append(document)
    categories = {words: classify(list(words)) for words in documents}
    folder = fresh_clone(tmp_path)
    failures, seconds = [], {}
    for words in (words for words, category in categories.items() if category == QUICK):
        problem, seconds[words] = run_documented(list(words), folder)
        if problem:
            failures.append(f"{', '.join(sorted(set(documents[words])))}: `{' '.join(words)}`: {problem}")
    counts = Counter(categories.values())
    slowest = max(seconds, key=seconds.get)
    print(f"{len(documents)} distinct commands: {dict(counts)}; "
          f"slowest quick: `{' '.join(slowest)}` {seconds[slowest]:.1f} s, all quick {sum(seconds.values()):.1f} s")
    outputs = set().union(*(declared_outputs(list(words)) for words in seconds))
    assert written_files(folder) <= outputs, "documented commands wrote what they do not name"
    assert not failures, "\n".join(failures)

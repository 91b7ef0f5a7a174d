"""Provenance of results/: every committed results file is stamped and current, or named in
results/KNOWN_STALE.md (which the README shows); and stamp / check on a scratch repository."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from studies import provenance
from studies.provenance import (KnownStaleRow, check, committed_results, known_stale, known_stale_pattern,
                                known_stale_row, load_manifest, module_sources, stamp)

ROOT = Path(__file__).resolve().parent.parent


def test_committed_results_are_current_or_known_stale() -> None:
    rows = known_stale(ROOT)
    stamps = load_manifest(ROOT)
    problems = [entry.describe() for entry in check(ROOT) if not known_stale_pattern(entry.path, rows)]
    problems += [f"{name}: no stamp in results/PROVENANCE.json -> regenerate it with its make target "
                 "(or name it in results/KNOWN_STALE.md)"
                 for name in committed_results(ROOT)
                 if name not in stamps and not known_stale_pattern(name, rows)]
    assert not problems, "stale results files:\n" + "\n".join(problems)


def test_known_stale_list_names_only_stale_committed_files() -> None:
    rows = known_stale(ROOT)
    committed = committed_results(ROOT)
    stale = {entry.path for entry in check(ROOT)}
    stamps = load_manifest(ROOT)
    unmatched = [pattern for pattern in rows
                 if not any(known_stale_pattern(name, {pattern: ""}) for name in committed)]
    assert not unmatched, f"KNOWN_STALE.md rows that name no committed results file: {unmatched}"
    current = [name for name in committed
               if known_stale_pattern(name, rows) and name in stamps and name not in stale]
    assert not current, f"regenerated and current, remove them from results/KNOWN_STALE.md: {current}"


def test_readme_shows_the_known_stale_list() -> None:
    sections = "".join(p.read_text() for p in sorted((ROOT / "docs" / "readme").glob("*.md")))
    assert "@include results/KNOWN_STALE.md" in sections
    listed = (ROOT / "results" / "KNOWN_STALE.md").read_text().strip().splitlines()
    assert listed[-1] in (ROOT / "README.md").read_text()


def test_every_make_target_writing_results_stamps_them() -> None:
    for mk in sorted((ROOT / "mk").glob("*.mk")):
        text = mk.read_text()
        writes = ("--out results" in text or "> results/" in text or "tee results/" in text
                  or "REPLAY_RESULTS)/" in text)
        if writes:
            assert "$(PROVENANCE_STAMP)" in text, f"{mk.name} writes results/ but stamps nothing"


# ---------------------------------------------------------------------------- scratch repo

def _git(root: Path, *args: str) -> None:
    subprocess.run(["git", *args], cwd=root, check=True, capture_output=True)


@pytest.fixture()
def repo(tmp_path: Path) -> Path:
    """A git repository with a package ``pkg`` (``study`` imports ``helper``, lazily
    ``plugin`` by name), a data file and one results file, all committed."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text('"""pkg."""\n')
    (tmp_path / "pkg" / "helper.py").write_text("VALUE = 1\n")
    (tmp_path / "pkg" / "plugin.py").write_text("NAME = 'p'\n")
    (tmp_path / "pkg" / "study.py").write_text(
        "import json\nfrom . import helper\n\ndef run():\n    import importlib\n"
        "    return importlib.import_module('pkg.plugin')\n")
    (tmp_path / "pkg" / "unused.py").write_text("X = 0\n")
    (tmp_path / "data.toml").write_text("a = 1\n")
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "out.md").write_text("| a |\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "add", ".")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
    return tmp_path


def test_module_sources_follow_project_imports(repo: Path) -> None:
    names = {p.relative_to(repo).as_posix() for p in module_sources(["pkg.study"], repo)}
    assert names == {"pkg/__init__.py", "pkg/study.py", "pkg/helper.py", "pkg/plugin.py"}


def test_stamp_then_check_finds_changed_inputs(repo: Path) -> None:
    new = stamp("results/out.md", "make out", inputs=["data.toml"], modules=["pkg.study"], root=repo)
    entry = new["results/out.md"]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                          text=True, check=True).stdout.strip()
    assert entry["commit"] == head  # only results/ changed: not dirty
    assert entry["command"] == "make out" and entry["inputs"] == ["data.toml"]
    assert check(repo) == []

    (repo / "pkg" / "unused.py").write_text("X = 1\n")  # not an input: still current
    assert check(repo) == []

    (repo / "data.toml").write_text("a = 2\n")
    [stale] = check(repo)
    assert stale.path == "results/out.md" and stale.command == "make out"
    assert "data.toml" in stale.describe() and "make out" in stale.describe()

    stamp("results/out.md", "make out", inputs=["data.toml"], modules=["pkg.study"], root=repo)
    assert check(repo) == []
    (repo / "pkg" / "plugin.py").write_text("NAME = 'q'\n")  # a lazily imported module
    [stale] = check(repo)
    assert "pkg/plugin.py" in stale.describe()


def test_a_rerun_with_the_same_inputs_and_output_leaves_the_manifest_untouched(repo: Path) -> None:
    """``make run`` twice, the second time at a later commit: the checkout stays clean."""
    stamp("results/out.md", "make out", inputs=["data.toml"], modules=["pkg.study"], root=repo)
    manifest = repo / "results" / "PROVENANCE.json"
    first = manifest.read_bytes()
    (repo / "notes.txt").write_text("a later commit\n")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "later")
    again = stamp("results/out.md", "make out", inputs=["data.toml"], modules=["pkg.study"], root=repo)
    assert manifest.read_bytes() == first
    assert again["results/out.md"]["commit"] == json.loads(first)["results"]["results/out.md"]["commit"]

    (repo / "results" / "out.md").write_text("| changed |\n")  # new output bytes: a new stamp
    stamp("results/out.md", "make out", inputs=["data.toml"], modules=["pkg.study"], root=repo)
    assert manifest.read_bytes() != first and check(repo) == []


def test_dirty_tree_is_marked_and_hand_edited_results_are_stale(repo: Path) -> None:
    (repo / "data.toml").write_text("a = 3\n")  # uncommitted change outside results/
    entry = stamp(repo / "results" / "out.md", "make out", inputs=["data.toml"], modules=[],
                  root=repo)["results/out.md"]
    assert entry["commit"].endswith("-dirty")
    (repo / "results" / "out.md").write_text("| b |\n")
    [stale] = check(repo)
    assert "changed since its stamp" in stale.describe()


def test_a_known_stale_row_is_its_paths_and_one_backticked_command() -> None:
    """The one parser of results/KNOWN_STALE.md's lines (provenance and restamp read the
    file through it): a row's paths and patterns, and None for the header, the separator,
    prose, and a row whose second cell is not exactly one command in backticks."""
    assert known_stale_row("| `results/run_*`, `results/out.md` | `make run` | long |") == \
        KnownStaleRow(("results/run_*", "results/out.md"), "make run")
    assert known_stale_row("  |`results/a.md`|`make a`|") == KnownStaleRow(("results/a.md",), "make a")
    for line in ("| Files | Regenerates them | Why |", "|---|---|---|", "", "Studies not rerun:",
                 "| `results/a.md` | `make a` and `make b` | two commands |",
                 "| `results/a.md` | make a | no backticks |", "| `results/a.md` |",
                 "| no path | `make a` | |", "`results/a.md` | `make a` | not a table row"):
        assert known_stale_row(line) is None, line


def test_known_stale_rows_and_errors(repo: Path) -> None:
    (repo / "results" / "KNOWN_STALE.md").write_text(
        "| Files | Regenerates them | Why |\n|---|---|---|\n"
        "| `results/run_*`, `results/out.md` | `make run` | long |\n")
    rows = known_stale(repo)
    assert rows == {"results/run_*": "make run", "results/out.md": "make run"}
    assert known_stale_pattern("results/run_a.png", rows) == "results/run_*"
    assert known_stale_pattern("results/other.md", rows) is None
    with pytest.raises(provenance.ProvenanceError, match="does not exist"):
        stamp("results/none.md", "make x", root=repo)
    with pytest.raises(provenance.ProvenanceError, match="no source file"):
        stamp("results/out.md", "make x", modules=["pkg.nothing"], root=repo)

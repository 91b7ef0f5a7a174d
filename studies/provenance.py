"""Provenance of the results files: what produced each, and whether it is still current.

Every results file written by a study is stamped in one committed manifest,
``results/PROVENANCE.json`` (keyed by the file's path from the repository root, so PNGs,
JSON and the Markdown tables the README includes are covered alike and stay clean). A
stamp records

- ``command``: the command that regenerates the file (``make handling``);
- ``commit``: ``git rev-parse HEAD`` when it was written, with ``-dirty`` when the working
  tree had changes outside ``results/``;
- ``inputs``: the data files it was computed from (artefact, tuning, vehicle, scenario
  and path files), and ``modules``: the study modules that produced it;
- ``sources``: the digest of each input file and of each source file of those modules
  and of every project module they import (transitively, see :func:`module_sources`);
- ``sha256``: one digest over all of those (:func:`combined_digest`);
- ``output_sha256``: the digest of the results file itself as written.

``python -m studies.provenance check`` recomputes the digests of every stamp and lists the
stale results files with the command that regenerates each: a file is stale when one of
its inputs or sources changed, or when the file itself changed without a new stamp.
``tests/test_results_provenance.py`` fails on a stale or unstamped committed results file
unless ``results/KNOWN_STALE.md`` names it (long studies that could not be rerun; the
README shows that list).

``python -m studies.provenance stamp FILE... --command CMD --inputs PATH... --modules
NAME...`` is what the make targets call after their study has written its files.
"""
from __future__ import annotations

import argparse
import ast
import fnmatch
import hashlib
import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

ROOT = Path(__file__).resolve().parent.parent
MANIFEST_NAME = "PROVENANCE.json"
KNOWN_STALE_NAME = "KNOWN_STALE.md"
#: Results files that are not study outputs (the manifest itself, the known-stale list).
BOOKKEEPING = (MANIFEST_NAME, KNOWN_STALE_NAME)
MISSING = "missing"
MANIFEST_VERSION = 1


class ProvenanceError(Exception):
    """A stamp cannot be made (no such results file, input or module)."""


@dataclass(frozen=True)
class StaleEntry:
    """A results file whose stamp no longer matches: ``reasons`` says what changed."""

    path: str
    command: str
    reasons: tuple[str, ...]

    def describe(self) -> str:
        """One line: the file, what changed and the command that regenerates it."""
        return f"{self.path}: {'; '.join(self.reasons)} -> regenerate with `{self.command}`"


# ---------------------------------------------------------------------------- digests

def file_digest(path: Path) -> str:
    """sha256 of the file's bytes (hex), or ``"missing"`` when it does not exist."""
    if not path.is_file():
        return MISSING
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def combined_digest(digests: dict[str, str]) -> str:
    """One sha256 over ``path -> digest`` pairs, independent of their order."""
    total = hashlib.sha256()
    for name in sorted(digests):
        total.update(f"{name}\0{digests[name]}\n".encode())
    return total.hexdigest()


# ---------------------------------------------------------------------------- modules

def project_packages(root: Path) -> frozenset[str]:
    """Top-level packages of the project: directories of ``root`` with an ``__init__.py``
    (the tests are not a producer of results and are left out)."""
    return frozenset(p.name for p in root.iterdir()
                     if p.is_dir() and (p / "__init__.py").is_file() and p.name != "tests")


def module_file(name: str, root: Path) -> Path | None:
    """The source file of project module ``name`` (``a.b`` -> ``a/b.py`` or
    ``a/b/__init__.py``), or None when there is none."""
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imported_names(tree: ast.AST, module: str, is_package: bool) -> set[str]:
    """Dotted names a module's source may import: ``import`` and ``from ... import``
    statements anywhere in it (lazy ones included), with ``from X import y`` giving both
    ``X`` and ``X.y``, and string literals that look like dotted module names (the lazy
    registries: ``importlib.import_module("controller.eso_dkmpc")``)."""
    names: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                if node.level > 1:
                    parts = parts[:len(parts) - node.level + 1]
                base = ".".join(p for p in parts + ([node.module] if node.module else []) if p)
            else:
                base = node.module or ""
            if base:
                names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names if base)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)+", node.value):
                names.add(node.value)
    return names


def module_sources(modules: Iterable[str], root: Path = ROOT) -> list[Path]:
    """Source files of ``modules`` and of every project module they import, transitively
    (the parent packages' ``__init__.py`` included, as importing runs them). Modules
    outside the project's packages (numpy, the standard library) are not followed.
    Raises ProvenanceError for a listed module that has no source file."""
    packages = project_packages(root)
    found: dict[str, Path] = {}
    pending: list[str] = []
    for name in modules:
        if module_file(name, root) is None:
            raise ProvenanceError(f"no source file for module {name!r} under {root}")
        pending.append(name)
    while pending:
        name = pending.pop()
        if name in found or name.split(".")[0] not in packages:
            continue
        path = module_file(name, root)
        if path is None:
            continue
        found[name] = path
        parts = name.split(".")
        pending.extend(".".join(parts[:i]) for i in range(1, len(parts)))
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        pending.extend(_imported_names(tree, name, path.name == "__init__.py"))
    return sorted(set(found.values()))


# ---------------------------------------------------------------------------- git

def git_commit(root: Path = ROOT) -> str:
    """``git rev-parse HEAD``, with ``-dirty`` when ``git status --porcelain`` shows a
    change outside ``results/``; ``"unknown"`` outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, check=True,
                              capture_output=True, text=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--", ".", ":(exclude)results"],
                                cwd=root, check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if status.strip() else "")


# ---------------------------------------------------------------------------- manifest

def _relative(path: Path | str, root: Path) -> str:
    """``path`` as a POSIX path relative to ``root`` (it must lie inside it)."""
    resolved = (root / path).resolve() if not Path(path).is_absolute() else Path(path).resolve()
    try:
        return resolved.relative_to(root.resolve()).as_posix()
    except ValueError:
        raise ProvenanceError(f"{path} is outside the repository {root}") from None


def manifest_path(root: Path = ROOT) -> Path:
    """Where the manifest lives: ``results/PROVENANCE.json``."""
    return root / "results" / MANIFEST_NAME


def load_manifest(root: Path = ROOT) -> dict[str, dict]:
    """The stamps of the manifest, keyed by results path (empty when there is none)."""
    path = manifest_path(root)
    if not path.is_file():
        return {}
    document = json.loads(path.read_text())
    return dict(document.get("results", {}))


def save_manifest(stamps: dict[str, dict], root: Path = ROOT) -> None:
    """Write the manifest, sorted, so its diffs stay small and reviewable."""
    path = manifest_path(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    document = {
        "about": "What produced each results file; python -m studies.provenance check lists "
                 "the stale ones (see studies/provenance.py).",
        "version": MANIFEST_VERSION,
        "results": {key: stamps[key] for key in sorted(stamps)},
    }
    path.write_text(json.dumps(document, indent=1, sort_keys=False) + "\n")


def input_digests(inputs: Sequence[str], modules: Sequence[str], root: Path = ROOT) -> dict[str, str]:
    """``path -> sha256`` of the data files ``inputs`` and the module sources."""
    files = {_relative(p, root) for p in inputs}
    files.update(_relative(p, root) for p in module_sources(modules, root))
    return {name: file_digest(root / name) for name in sorted(files)}


def stamp(paths: Path | str | Sequence[Path | str], command: str, inputs: Sequence[Path | str] = (),
          modules: Sequence[str] = (), root: Path = ROOT) -> dict[str, dict]:
    """Record in the manifest that ``command`` produced the results file(s) ``paths`` from
    the data files ``inputs`` and the modules ``modules`` (their sources and those of the
    project modules they import). Call it after the files are written. Returns the new
    stamps by results path. Raises ProvenanceError for a results file or a data input
    that does not exist, or a module without a source file."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    results = [_relative(p, root) for p in paths]
    for name in results:
        if not (root / name).is_file():
            raise ProvenanceError(f"results file {name} does not exist (stamp it after writing it)")
    input_names = sorted({_relative(p, root) for p in inputs})
    for name in input_names:
        if not (root / name).is_file():
            raise ProvenanceError(f"input file {name} does not exist")
    digests = input_digests(input_names, modules, root)
    commit = git_commit(root)
    new = {}
    for name in results:
        new[name] = {
            "command": command,
            "commit": commit,
            "inputs": input_names,
            "modules": sorted(set(modules)),
            "sha256": combined_digest(digests),
            "output_sha256": file_digest(root / name),
            "sources": {key: value[:16] for key, value in digests.items()},
        }
    stamps = load_manifest(root)
    if all(_same_but_commit(stamps.get(name), entry) for name, entry in new.items()):
        return {name: stamps[name] for name in new}  # nothing new: the manifest stays as it is
    stamps.update(new)
    save_manifest(stamps, root)
    return new


def _same_but_commit(old: dict | None, new: dict) -> bool:
    """True when ``old`` records the same command, inputs and output bytes as ``new``: a
    rerun that wrote the same file from the same sources leaves its stamp (and with it the
    checkout) untouched, whatever commit it ran at."""
    if old is None:
        return False
    return {k: v for k, v in old.items() if k != "commit"} == {k: v for k, v in new.items() if k != "commit"}


def check(root: Path = ROOT) -> list[StaleEntry]:
    """Every stamped results file whose inputs, sources or own content changed since its
    stamp (or which no longer exists), with the command that regenerates it."""
    stale = []
    for name, entry in sorted(load_manifest(root).items()):
        reasons: list[str] = []
        if not (root / name).is_file():
            reasons.append("the results file is missing")
        elif file_digest(root / name) != entry.get("output_sha256"):
            reasons.append("the file changed since its stamp (written without stamping)")
        try:
            digests = input_digests(entry.get("inputs", []), entry.get("modules", []), root)
        except ProvenanceError as exc:
            reasons.append(str(exc))
        else:
            if combined_digest(digests) != entry.get("sha256"):
                recorded = entry.get("sources", {})
                changed = sorted(key for key in set(digests) | set(recorded)
                                 if digests.get(key, MISSING)[:16] != recorded.get(key, MISSING)[:16])
                shown = ", ".join(changed[:6]) + (f" and {len(changed) - 6} more" if len(changed) > 6 else "")
                reasons.append(f"inputs changed: {shown or 'digest differs'}")
        if reasons:
            stale.append(StaleEntry(name, entry.get("command", "?"), tuple(reasons)))
    return stale


# ---------------------------------------------------------------------------- known stale

@dataclass(frozen=True)
class KnownStaleRow:
    """One row of ``results/KNOWN_STALE.md``: the results paths or ``fnmatch`` patterns it
    names and the command that regenerates them."""

    files: tuple[str, ...]
    command: str


def known_stale_row(line: str) -> KnownStaleRow | None:
    """The row that a line of ``results/KNOWN_STALE.md`` is, or None for any other line
    (the text above the table, its header and separator). The file is a Markdown table:
    the first cell holds one or more paths in backticks (``fnmatch`` patterns allowed:
    `results/run_*`), the second the command in backticks, the third why it was not
    regenerated."""
    if not line.lstrip().startswith("|"):
        return None
    cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
    if len(cells) < 2:
        return None
    command = re.fullmatch(r"`([^`]+)`", cells[1])
    files = tuple(re.findall(r"`([^`]+)`", cells[0]))
    if command is None or not files:
        return None
    return KnownStaleRow(files, command.group(1))


def known_stale(root: Path = ROOT) -> dict[str, str]:
    """``results/KNOWN_STALE.md``'s rows (:func:`known_stale_row`): results path or pattern
    -> the command that regenerates it."""
    path = root / "results" / KNOWN_STALE_NAME
    if not path.is_file():
        return {}
    rows = {}
    for line in path.read_text().splitlines():
        row = known_stale_row(line)
        if row is not None:
            rows.update(dict.fromkeys(row.files, row.command))
    return rows


def known_stale_pattern(name: str, rows: dict[str, str]) -> str | None:
    """The pattern of ``rows`` (see :func:`known_stale`) naming results file ``name``."""
    return next((pattern for pattern in rows if fnmatch.fnmatchcase(name, pattern)), None)


def committed_results(root: Path = ROOT) -> list[str]:
    """Results files tracked by git (the manifest and the known-stale list excepted)."""
    listing = subprocess.run(["git", "ls-files", "--", "results"], cwd=root, check=True,
                             capture_output=True, text=True).stdout.split()
    return sorted(name for name in listing
                  if Path(name).name not in BOOKKEEPING or Path(name).parent.as_posix() != "results")


# ---------------------------------------------------------------------------- CLI

def main(argv: list[str] | None = None) -> int:
    """CLI entry point (``stamp`` and ``check``); returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m studies.provenance",
                                     description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True)
    stamp_parser = sub.add_parser("stamp", help="stamp results files after a study wrote them")
    stamp_parser.add_argument("files", nargs="+", type=Path, help="results files just written")
    stamp_parser.add_argument("--command", required=True, help="the command that regenerates them")
    stamp_parser.add_argument("--inputs", nargs="*", default=[], type=Path,
                              help="data files read (artefact, tuning, vehicle, scenario, path files)")
    stamp_parser.add_argument("--modules", nargs="*", default=[],
                              help="modules that produce them (their imports are followed)")
    check_parser = sub.add_parser("check", help="list stale results files with their commands")
    check_parser.add_argument("--all", action="store_true",
                              help="also list the stale files named in results/KNOWN_STALE.md")
    args = parser.parse_args(argv)
    try:
        if args.action == "stamp":
            new = stamp(args.files, args.command, args.inputs, args.modules)
            commit = next(iter(new.values()))["commit"]
            print(f"stamped {len(new)} results file(s) at {commit}: `{args.command}`")
            return 0
        listed = known_stale()
        stale = check()
        shown = [entry for entry in stale if args.all or not known_stale_pattern(entry.path, listed)]
        for entry in shown:
            note = " (known stale)" if known_stale_pattern(entry.path, listed) else ""
            print(entry.describe() + note)
        stamps = load_manifest()
        unstamped = [name for name in committed_results()
                     if name not in stamps and not known_stale_pattern(name, listed)]
        for name in unstamped:
            print(f"{name}: no stamp in results/{MANIFEST_NAME} and not in results/{KNOWN_STALE_NAME}")
        if not shown and not unstamped:
            named = sum(1 for name in committed_results() if known_stale_pattern(name, listed))
            print(f"{len(stamps)} stamped results files current; {named} committed ones known stale "
                  f"(results/{KNOWN_STALE_NAME})")
        return 1 if any(not known_stale_pattern(e.path, listed) for e in stale) or unstamped else 0
    except ProvenanceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

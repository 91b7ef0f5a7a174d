"""``python -m studies.results_compare REV [FILES...]``: are the results of the working tree
the ones of commit REV, apart from what depends on the machine?

A refactor that must keep behaviour is checked by rerunning the studies and comparing
their ``results/`` files with those of the commit before it. The JSON and CSV files are
compared value by value, leaving out every field whose name says it is a wall-clock figure
(:data:`MACHINE_WORDS`: task and solver times, wall time, overruns, the machine) and the
campaigns' cache keys (:data:`BOOKKEEPING_FIELDS`); any other
difference, to the last bit, is listed. Other files (Markdown, PNG) are counted as changed
or not: their timing lines move from run to run. Two kinds of machine figures have no
telling name and are listed with the rest: the detection times (``at_ms``) of the fault
cases that run on the wall clock (the lost bus, the time jump) and the text of the timing
checks (``detail``, "0.24 ms vs 0.22 ms").

Exit status: 0 when every compared value is equal, 1 when one differs or a file is missing
on one side, 2 for bad arguments (an unknown revision).
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: A field whose name holds one of these is a machine figure, not a result.
#: (``log_sha256``: a CAN log starts with the wall-clock time it was recorded at.)
MACHINE_WORDS = ("time", "wall", "seconds", "_us", "max_ms", "mean_ms", "median_ms", "share", "overrun",
                 "machine", "cpu", "p50", "p99", "mean_s", "median_s", "max_s", "lateness", "steal",
                 "load", "took", "log_sha256")


#: Fields that name how a result was computed, not what it is: a campaign cell's cache key
#: hashes the code, so any change to a source file changes it.
BOOKKEEPING_FIELDS = ("key",)


def is_machine_field(name: str) -> bool:
    """Whether the field ``name`` holds a wall-clock or machine figure, or bookkeeping."""
    lowered = name.lower()
    return lowered in BOOKKEEPING_FIELDS or any(word in lowered for word in MACHINE_WORDS)


def differences(old: Any, new: Any, where: str = "") -> Iterator[str]:
    """Each place where the JSON values ``old`` and ``new`` differ, machine fields left out."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new), key=str):
            if is_machine_field(str(key)):
                continue
            if key not in old or key not in new:
                yield f"{where}.{key}: only in {'the working tree' if key in new else 'REV'}"
            else:
                yield from differences(old[key], new[key], f"{where}.{key}")
    elif isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            yield f"{where}: {len(old)} items, now {len(new)}"
        for i, (a, b) in enumerate(zip(old, new)):
            yield from differences(a, b, f"{where}[{i}]")
    elif old != new and not (old != old and new != new):  # NaN equals NaN here
        yield f"{where}: {old!r} -> {new!r}"


def csv_rows(text: str) -> list[dict[str, str]]:
    """A CSV file's rows without its machine columns."""
    return [{k: v for k, v in row.items() if not is_machine_field(k)}
            for row in csv.DictReader(io.StringIO(text))]


def file_at(revision: str, name: str) -> bytes | None:
    """The bytes of ``name`` at ``revision`` (None when it has no such file)."""
    shown = subprocess.run(["git", "show", f"{revision}:{name}"], cwd=ROOT, capture_output=True)
    return shown.stdout if shown.returncode == 0 else None


def compare_file(revision: str, name: str) -> list[str]:
    """The differences of one results file (see the module docstring)."""
    before = file_at(revision, name)
    path = ROOT / name
    if before is None or not path.is_file():
        return [f"{name}: {'not at ' + revision if before is None else 'not in the working tree'}"]
    after = path.read_bytes()
    if name.endswith(".json"):
        return [f"{name}{d}" for d in differences(json.loads(before), json.loads(after))]
    if name.endswith(".csv"):
        old, new = csv_rows(before.decode()), csv_rows(after.decode())
        return [f"{name}{d}" for d in differences(old, new)]
    return []


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m studies.results_compare", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision", help="the commit to compare with (e.g. HEAD~5, a hash)")
    parser.add_argument("files", nargs="*", help="results files (default: every JSON and CSV file "
                                                 "under results/ at that commit)")
    args = parser.parse_args(argv)
    listed = subprocess.run(["git", "ls-tree", "-r", "--name-only", args.revision, "results/"], cwd=ROOT,
                            capture_output=True, text=True)
    if listed.returncode != 0:
        print(f"error: {args.revision}: not a revision of this repository", file=sys.stderr)
        return 2
    names = args.files or [n for n in listed.stdout.split() if n.endswith((".json", ".csv"))
                           and not n.endswith("PROVENANCE.json")]
    problems = [line for name in names for line in compare_file(args.revision, name)]
    others = [n for n in listed.stdout.split() if not n.endswith((".json", ".csv"))]
    moved = [n for n in others if (ROOT / n).is_file() and file_at(args.revision, n) != (ROOT / n).read_bytes()]
    for line in problems[:200]:
        print(line)
    if len(problems) > 200:
        print(f"... {len(problems) - 200} more")
    print(f"{len(names)} JSON / CSV files compared with {args.revision}: "
          f"{len(problems)} differences outside machine figures; "
          f"{len(moved)} of {len(others)} other files changed bytes (timing lines, figures)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())

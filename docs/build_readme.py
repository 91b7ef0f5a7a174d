"""Assemble README.md from the sections in docs/readme/ (``make readme``).

The README is short (at most 300 lines, checked by ``tests/test_build_readme.py``): what
the project is, the two commands, a tour, the layout and one paragraph per capability
linking to its manual ``docs/<capability>.md``. The sections live in their own files so
parallel work does not collide; this joins them in file-name order and puts a contents
list after the introduction.

A line ``@include results/FILE.md`` in a section is replaced by that file, as the make
target named beside it last wrote it: tables of measured figures are never copied by hand,
so the README cannot drift from ``results/``. ``@include results/FILE.md#Heading`` takes
only the part under that heading (without the heading line), up to the next heading of
the same or a higher level. Headings of the included text are moved down
so that its top level is ``####`` (they stay out of the contents list). A missing file
stops the build, naming the section and the file.
"""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SECTIONS = ROOT / "docs" / "readme"


def _anchor(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens."""
    slug = re.sub(r"[^\w\- ]", "", title.strip().lower())
    return slug.replace(" ", "-")


INCLUDE = re.compile(r"^@include ([^\s#]+)(?:#(.+?))?\s*$", re.MULTILINE)


class ReadmeError(Exception):
    """A section includes a file that does not exist (or escapes the repository)."""


def expand_includes(text: str, section: Path) -> str:
    """``text`` with every ``@include PATH`` line replaced by the file (path from the repo root)."""
    def replace(match: re.Match[str]) -> str:
        target = (ROOT / match.group(1)).resolve()
        if ROOT not in target.parents or not target.is_file():
            raise ReadmeError(f"{section.name}: @include {match.group(1)}: no such file in the repository "
                              "(run the make target that writes it)")
        text = target.read_text()
        if match.group(2) is not None:
            text = heading_part(text, match.group(2).strip(), f"{section.name}: @include {match.group(0)[9:]}")
        return demote_headings(text.strip())

    return INCLUDE.sub(replace, text)


HEADING = re.compile(r"^(#{1,6}) ", re.MULTILINE)


def heading_part(text: str, title: str, where: str) -> str:
    """The lines under the heading ``title`` up to the next heading of its level or above."""
    lines = text.splitlines()
    for start, line in enumerate(lines):
        found = HEADING.match(line)
        if found and line[found.end():].strip() == title:
            level = len(found.group(1))
            end = next((i for i in range(start + 1, len(lines))
                        if (m := HEADING.match(lines[i])) and len(m.group(1)) <= level), len(lines))
            return "\n".join(lines[start + 1:end])
    raise ReadmeError(f"{where.strip()}: no heading {title!r} in the file")
#: Level of an included file's top heading in the README.
INCLUDED_TOP_LEVEL = 4


def demote_headings(text: str) -> str:
    """Shift every ATX heading so the highest one in ``text`` becomes level 4 (never above 6)."""
    levels = [len(m.group(1)) for m in HEADING.finditer(text)]
    if not levels:
        return text
    shift = max(0, INCLUDED_TOP_LEVEL - min(levels))
    return HEADING.sub(lambda m: "#" * min(6, len(m.group(1)) + shift) + " ", text)


def build() -> str:
    parts = [expand_includes(p.read_text(), p).rstrip() + "\n" for p in sorted(SECTIONS.glob("*.md"))]
    titles = [
        line[3:] for part in parts[1:] for line in part.splitlines() if line.startswith("## ")
    ]
    contents = "## Contents\n\n" + "".join(f"- [{t}](#{_anchor(t)})\n" for t in titles)
    return "\n".join([parts[0], contents, *parts[1:]])


if __name__ == "__main__":
    try:
        text = build()
    except ReadmeError as e:
        raise SystemExit(f"error: {e}") from None
    (ROOT / "README.md").write_text(text)
    print(f"wrote README.md from {len(list(SECTIONS.glob('*.md')))} sections")

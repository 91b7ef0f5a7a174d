"""Assemble README.md from the per-capability sections in docs/readme/ (``make readme``).

Each capability keeps its section in its own file so parallel work does not collide; this
joins them in file-name order and puts a contents list after the introduction.
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


def build() -> str:
    parts = [p.read_text().rstrip() + "\n" for p in sorted(SECTIONS.glob("*.md"))]
    titles = [
        line[3:] for part in parts[1:] for line in part.splitlines() if line.startswith("## ")
    ]
    contents = "## Contents\n\n" + "".join(f"- [{t}](#{_anchor(t)})\n" for t in titles)
    return "\n".join([parts[0], contents, *parts[1:]])


if __name__ == "__main__":
    (ROOT / "README.md").write_text(build())
    print(f"wrote README.md from {len(list(SECTIONS.glob('*.md')))} sections")

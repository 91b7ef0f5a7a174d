"""README assembly: ``@include`` of results files, the committed README is current and short,
its links and the manuals' resolve, and the manuals link to results instead of copying them."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _builder():
    spec = importlib.util.spec_from_file_location("build_readme", ROOT / "docs" / "build_readme.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_include_is_replaced_by_the_file_and_a_missing_file_is_named() -> None:
    builder = _builder()
    section = Path("docs/readme/99-x.md")
    text = "before\n@include results/table2_high_mu.md\nafter\n"
    expanded = builder.expand_includes(text, section)
    table = (ROOT / "results" / "table2_high_mu.md").read_text().rstrip()
    assert table.startswith("### Table II")
    assert expanded == f"before\n#{table}\nafter\n"  # its ### heading becomes ####
    assert "inline @include results/x.md stays" == builder.expand_includes(
        "inline @include results/x.md stays", section)
    for missing in ("results/no_such_table.md", "../outside.md"):
        with pytest.raises(builder.ReadmeError, match=f"99-x.md: @include {missing}"):
            builder.expand_includes(f"@include {missing}\n", section)


def test_include_of_one_part_stops_at_the_next_heading_of_its_level() -> None:
    builder = _builder()
    text = "# T\nintro\n## A\na1\n### A.1\na2\n## B\nb\n"
    assert builder.heading_part(text, "A", "x") == "a1\n### A.1\na2"
    assert builder.heading_part(text, "B", "x") == "b"
    with pytest.raises(builder.ReadmeError, match="no heading 'C'"):
        builder.heading_part(text, "C", "x")
    summary = builder.expand_includes("@include results/timing.md#Summary\n", Path("95-x.md"))
    assert summary.startswith("| load | controller |") and "## Goals" not in summary


def test_included_headings_move_below_the_sections() -> None:
    builder = _builder()
    assert builder.demote_headings("# A\n## B\ntext #1\n###### deep") == "#### A\n##### B\ntext #1\n###### deep"
    assert builder.demote_headings("#### already\n") == "#### already\n"
    assert builder.demote_headings("no heading") == "no heading"


def test_committed_readme_is_the_assembled_one() -> None:
    """README.md equals what ``make readme`` writes now: sections and included results agree."""
    assert (ROOT / "README.md").read_text() == _builder().build(), "README.md is stale: run make readme"


README_MAX_LINES = 300
DOCS = ROOT / "docs"
#: Markdown links ``[text](target)``; the target without its ``#anchor``.
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.glob("*.md")), *sorted((DOCS / "readme").glob("*.md"))]


def _anchors(path: Path) -> set[str]:
    builder = _builder()
    return {builder._anchor(line.lstrip("#")) for line in path.read_text().splitlines()
            if re.match(r"^#{1,6} ", line)}


def test_readme_is_at_most_300_lines() -> None:
    lines = (ROOT / "README.md").read_text().count("\n")
    print(f"README.md: {lines} lines")
    assert lines <= README_MAX_LINES, (f"README.md has {lines} lines (at most {README_MAX_LINES}): "
                                       "move the detail into a manual docs/<capability>.md")


def test_every_relative_link_of_the_readme_and_the_manuals_resolves() -> None:
    broken = []
    for document in _markdown_files():
        base = ROOT if document.parent == DOCS / "readme" else document.parent
        for target in LINK.findall(document.read_text()):
            if re.match(r"^[a-z]+:", target):
                continue  # http(s), mailto: not checked here
            path_part, _, anchor = target.partition("#")
            linked = (base / path_part).resolve() if path_part else document
            if not linked.exists():
                broken.append(f"{document.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
                broken.append(f"{document.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_manual_is_linked_from_the_readme() -> None:
    readme = (ROOT / "README.md").read_text()
    unlinked = [manual.name for manual in sorted(DOCS.glob("*.md")) if f"](docs/{manual.name}" not in readme]
    assert not unlinked, f"manuals the README does not link to: {unlinked}"


def test_the_sources_and_the_manuals_never_copy_a_results_table() -> None:
    """Tables of results/ reach the docs only by ``@include`` (README) or by a link."""
    rows = {line.strip() for result in (ROOT / "results").rglob("*.md")
            for line in result.read_text().splitlines()
            if line.startswith("|") and re.search(r"\d", line) and not set(line) <= set("|-: ")}
    copies = [f"{document.relative_to(ROOT)}: {line.strip()[:80]}"
              for document in _markdown_files()[1:] for line in document.read_text().splitlines()
              if line.strip() in rows]
    assert not copies, "copied results rows (include or link the results file instead):\n" + "\n".join(copies)

"""README assembly: ``@include`` of results files, and the committed README is current."""
from __future__ import annotations

import importlib.util
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

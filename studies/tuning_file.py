"""Targeted edits of the tuning file (``controller/tuning.toml``): chosen values written
into their tables in place, with a comment line naming them; every other line is kept.

Used by ``make tune`` (``studies.tuning_sweep``), ``make tune-observer``
(``studies.observer_tuning``) and ``studies.unscheduled_tuning``.
"""
from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path

from hil.errors import StudyError
from studies.tuning_sweep_grids import Setting

#: The comment the written tuning tables carry.
TUNING_COMMENT = "chosen by make tune on the tuning set, results/tuning_sweep.md"

_SECTION = re.compile(r"^\s*\[([^\]]+)\]\s*(#.*)?$")
_ASSIGNMENT = re.compile(r"^(?P<key>\s*(?P<name>[A-Za-z0-9_-]+)\s*=\s*)(?P<value>[^#\n]*?)(?P<rest>\s*(#.*)?)$")


def format_value(value: float) -> str:
    """A TOML float literal for ``value`` (``10.0``, ``0.97``, ``1e-3`` as Python writes it)."""
    text = repr(float(value))
    return text if any(c in text for c in ".en") else text + ".0"


def update_tuning_text(text: str, chosen: Mapping[str, Setting], comment: str = TUNING_COMMENT) -> str:
    """The tuning file ``text`` with, in each table ``[name]`` of ``chosen``, the values of
    that setting's fields replaced in place (spacing and trailing comments kept) and one
    comment line ``# <fields>: <comment>`` right under the table header (replacing an
    earlier one that ends with ``comment``). Every other line is unchanged.

    Raises:
        StudyError: a table or field of ``chosen`` is not in ``text``, or the result does
            not parse back to the chosen values.
    """
    lines = text.splitlines(keepends=True)
    sections: dict[str, tuple[int, int]] = {}
    current, start = None, 0
    for i, line in enumerate(lines):
        match = _SECTION.match(line)
        if match:
            if current is not None:
                sections[current] = (start, i)
            current, start = match.group(1).strip().strip('"'), i
    if current is not None:
        sections[current] = (start, len(lines))
    insertions: list[tuple[int, str, int | None]] = []
    for table, setting in chosen.items():
        if table not in sections:
            raise StudyError(f"tuning file has no table [{table}]")
        first, end = sections[table]
        remaining = dict(setting)
        existing_comment = None
        for i in range(first + 1, end):
            line = lines[i]
            if line.lstrip().startswith("#") and line.rstrip().endswith(comment):
                existing_comment = i
                continue
            match = _ASSIGNMENT.match(line.rstrip("\n"))
            if match and match.group("name") in remaining:
                newline = "\n" if line.endswith("\n") else ""
                value_text = format_value(remaining.pop(match.group("name")))
                rest = match.group("rest")
                comment_text = rest.lstrip()
                if comment_text:
                    # Keep the trailing comment's column (at least one space before it).
                    column = len(match.group("key")) + len(match.group("value")) + len(rest) - len(comment_text)
                    gap = max(1, column - len(match.group("key")) - len(value_text))
                    rest = " " * gap + comment_text
                lines[i] = match.group("key") + value_text + rest + newline
        if remaining:
            raise StudyError(f"tuning file table [{table}] has no field(s) {sorted(remaining)}")
        note = f"# {', '.join(name for name, _ in setting)}: {comment}\n"
        insertions.append((first + 1, note, existing_comment))
    for position, note, existing in sorted(insertions, key=lambda item: item[0], reverse=True):
        if existing is not None:
            lines[existing] = note
        else:
            lines.insert(position, note)
    result = "".join(lines)
    try:
        document = tomllib.loads(result)
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"edited tuning file is not valid TOML: {e}") from e
    for table, setting in chosen.items():
        for name, value in setting:
            if document[table][name] != value:
                raise StudyError(f"[{table}] {name}: wrote {value!r}, reads back {document[table][name]!r}")
    return result


def write_tuning_file(path: Path, chosen: Mapping[str, Setting]) -> None:
    """Re-read ``path`` now and write it back with :func:`update_tuning_text`'s edits
    (others may have changed other tables since the sweep started)."""
    text = path.read_text(encoding="utf-8")
    updated = update_tuning_text(text, chosen)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(updated, encoding="utf-8")
    os.replace(temporary, path)


"""A TOML writer for the documents the campaign writes (a cell's scenario): scalars, arrays of
scalars, tables and arrays of tables; floats with ``repr`` so that they read back bit for
bit (``tomllib`` reads, the standard library has no writer).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def to_toml(document: Mapping[str, Any]) -> str:
    """A TOML text of ``document`` (scalars, arrays of scalars, tables, arrays of tables);
    floats written with ``repr`` so they read back bit for bit."""
    lines: list[str] = []
    _write_table(lines, document, ())
    return "\n".join(lines).lstrip("\n") + "\n"


def _key(name: str) -> str:
    return name if name.replace("_", "").replace("-", "").isalnum() else _scalar(name)


def _scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "inf" if value > 0 else "-inf" if value < 0 else "nan"
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_scalar(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_scalar(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {value!r} as TOML")


def _write_table(lines: list[str], table: Mapping[str, Any], prefix: tuple[str, ...]) -> None:
    tables = {k: v for k, v in table.items() if isinstance(v, Mapping)}
    arrays = {k: v for k, v in table.items()
              if isinstance(v, list) and v and all(isinstance(i, Mapping) for i in v)}
    for key, value in table.items():
        if key not in tables and key not in arrays:
            lines.append(f"{_key(key)} = {_scalar(value)}")
    for key, value in tables.items():
        lines.append("")
        lines.append("[" + ".".join(_key(k) for k in (*prefix, key)) + "]")
        _write_table(lines, value, (*prefix, key))
    for key, items in arrays.items():
        for item in items:
            lines.append("")
            lines.append("[[" + ".".join(_key(k) for k in (*prefix, key)) + "]]")
            _write_table(lines, item, (*prefix, key))

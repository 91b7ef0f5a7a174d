"""The tables of ``docs/can-contract.md``, generated from the DBC so they cannot drift.

The document's prose is written by hand; its node, frame and signal tables sit between
marker comments and are rewritten from ``can_defs/vehicle.dbc``:

    <!-- BEGIN GENERATED frames: python -m can_defs.contract_tables -->
    ...
    <!-- END GENERATED frames -->

Usage::

    python -m can_defs.contract_tables            # rewrite the tables in docs/can-contract.md
    python -m can_defs.contract_tables --check    # exit 1 (naming the tables) if stale

``tests/test_contract_doc.py`` fails when the committed tables differ from the DBC.
Build-time tool: the ECU never imports it.
"""
from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import cantools

from can_defs.dbc import DBC_PATH, load_database
from can_defs.errors import CanDefsError

Database = cantools.database.can.Database

#: The document whose tables this module writes.
CONTRACT_DOC = Path(__file__).resolve().parent.parent / "docs" / "can-contract.md"
#: The command that regenerates the tables (named in markers and error messages).
COMMAND = "python -m can_defs.contract_tables"

#: The E2E signals every protected frame carries in bytes 0 and 1.
E2E_SIGNALS = ("CRC", "CNT")


class ContractDocError(CanDefsError):
    """The contract document lacks a marker pair, or holds one twice."""


def _number(value: float | int | None) -> str:
    """A DBC number as written in the DBC: integers without a point, others shortest."""
    if value is None:
        return "-"
    if float(value).is_integer():
        return str(int(value))
    return repr(float(value))


def _cell(text: str | None) -> str:
    """Table cell text: one line, pipes escaped, '-' when empty."""
    if not text:
        return "-"
    return " ".join(text.split()).replace("|", "\\|")


def _table(header: Iterable[str], rows: Iterable[Iterable[str]]) -> str:
    header = list(header)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines.extend("| " + " | ".join(_cell(cell) for cell in row) + " |" for row in rows)
    return "\n".join(lines)


def _receivers(database: Database, message: cantools.database.can.Message) -> list[str]:
    """Receiving nodes of a frame: the union over its signals, in the DBC's node order."""
    names = {receiver for signal in message.signals for receiver in signal.receivers}
    return [node.name for node in database.nodes if node.name in names]


def _period(message: cantools.database.can.Message) -> str:
    if message.cycle_time:
        return f"{message.cycle_time} ms"
    return "event" if message.send_type == "Event" else "-"


def _messages(database: Database) -> list[cantools.database.can.Message]:
    return sorted(database.messages, key=lambda message: message.frame_id)


def nodes_table(database: Database) -> str:
    """Markdown table of the DBC's nodes (BU_) with their comments, and the bus line."""
    attributes = database.dbc.attributes if database.dbc is not None else {}
    baud = attributes.get("Baudrate")
    bus = (f"DBC version `{database.version}`, bus type "
           f"{attributes['BusType'].value if 'BusType' in attributes else '-'}, "
           f"{int(baud.value) // 1000 if baud is not None else '-'} kbit/s.")
    sends = {node.name: [m.name for m in _messages(database) if node.name in m.senders]
             for node in database.nodes}
    rows = [(f"`{node.name}`", node.comment, ", ".join(sends[node.name]))
            for node in database.nodes]
    return bus + "\n\n" + _table(("node", "role", "sends"), rows)


def frames_table(database: Database) -> str:
    """Markdown table of the frames: ID, name, sender, receivers, period, length, E2E, notes."""
    rows = []
    for message in _messages(database):
        names = [signal.name for signal in message.signals]
        protected = all(name in names for name in E2E_SIGNALS)
        payload = [name for name in names if name not in E2E_SIGNALS]
        rows.append((f"`0x{message.frame_id:03X}`", f"`{message.name}`", ", ".join(message.senders),
                     ", ".join(_receivers(database, message)), _period(message), str(message.length),
                     "CRC, CNT" if protected else "none", ", ".join(payload), message.comment))
    return _table(("ID", "frame", "sender", "receivers", "period", "bytes", "E2E", "payload signals",
                   "notes"), rows)


def signals_table(database: Database) -> str:
    """Markdown table of every signal: bit layout, scaling, unit, range, values, meaning."""
    rows = []
    for message in _messages(database):
        for signal in sorted(message.signals, key=lambda s: s.start):
            if signal.byte_order != "little_endian":
                raise ContractDocError(f"{message.name}.{signal.name}: the contract is little-endian only")
            choices = ", ".join(f"{int(value)} {name}" for value, name in (signal.choices or {}).items())
            rows.append((message.name, f"`{signal.name}`", str(signal.start), str(signal.length),
                         "yes" if signal.is_signed else "no", _number(signal.scale),
                         _number(signal.offset), signal.unit or "-",
                         f"{_number(signal.minimum)} .. {_number(signal.maximum)}", choices,
                         signal.comment))
    return _table(("frame", "signal", "start bit", "length", "signed", "factor", "offset", "unit",
                   "range", "values", "meaning"), rows)


#: The generated blocks of the document, by marker name.
TABLES: dict[str, Callable[[Database], str]] = {
    "nodes": nodes_table,
    "frames": frames_table,
    "signals": signals_table,
}


def _block(name: str) -> re.Pattern[str]:
    return re.compile(rf"(<!-- BEGIN GENERATED {name}:[^>]*-->\n)(.*?)(<!-- END GENERATED {name} -->)",
                      re.DOTALL)


def generated_blocks(text: str) -> dict[str, str]:
    """The current contents of each generated block of ``text``, by name."""
    blocks = {}
    for name in TABLES:
        found = _block(name).findall(text)
        if len(found) != 1:
            raise ContractDocError(
                f"{len(found)} blocks '<!-- BEGIN GENERATED {name}: {COMMAND} -->' ... "
                f"'<!-- END GENERATED {name} -->' in the document, expected 1")
        blocks[name] = found[0][1]
    return blocks


def render(text: str, database: Database | None = None) -> str:
    """``text`` with every generated block rewritten from ``database`` (the DBC by default)."""
    database = database if database is not None else load_database(DBC_PATH)
    generated_blocks(text)  # every marker pair present exactly once
    for name, make in TABLES.items():
        body = make(database).rstrip("\n") + "\n"
        text = _block(name).sub(lambda m, body=body: m.group(1) + body + m.group(3), text)
    return text


def stale_tables(doc: Path = CONTRACT_DOC, database: Database | None = None) -> list[str]:
    """Names of the generated blocks of ``doc`` that differ from the DBC's tables."""
    text = doc.read_text(encoding="utf-8")
    fresh = generated_blocks(render(text, database))
    return [name for name, body in generated_blocks(text).items() if body != fresh[name]]


def main(argv: list[str] | None = None) -> int:
    """CLI: rewrite (or with ``--check`` verify) the tables of the contract document."""
    parser = argparse.ArgumentParser(prog=COMMAND, description=__doc__.split("\n\n")[0])
    parser.add_argument("--doc", type=Path, default=CONTRACT_DOC, help="document to update")
    parser.add_argument("--check", action="store_true",
                        help="only check; exit 1 when a table differs from the DBC")
    args = parser.parse_args(argv)
    try:
        if args.check:
            stale = stale_tables(args.doc)
            if stale:
                print(f"error: {args.doc}: tables {', '.join(stale)} differ from {DBC_PATH.name}; "
                      f"run {COMMAND}", file=sys.stderr)
                return 1
            print(f"{args.doc}: tables match {DBC_PATH.name}")
            return 0
        text = args.doc.read_text(encoding="utf-8")
        args.doc.write_text(render(text), encoding="utf-8")
    except (OSError, CanDefsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote the {', '.join(TABLES)} tables of {args.doc} from {DBC_PATH.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""docs/can-contract.md: its generated tables equal what the DBC gives, and the ECU and the
code point to it (not to a spec outside the repository)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from can_defs import contract_tables
from can_defs.dbc import DBC_PATH, load_database
from firmware_sim.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "can-contract.md"
REGENERATE = "python -m can_defs.contract_tables (make contract-tables)"


def test_committed_tables_are_the_ones_the_dbc_gives() -> None:
    stale = contract_tables.stale_tables(DOC)
    assert not stale, (f"docs/can-contract.md: tables {', '.join(stale)} differ from "
                       f"can_defs/vehicle.dbc; regenerate them with {REGENERATE}")


def test_every_frame_and_signal_of_the_dbc_is_in_the_tables() -> None:
    blocks = contract_tables.generated_blocks(DOC.read_text())
    database = load_database()
    for message in database.messages:
        assert f"`0x{message.frame_id:03X}` | `{message.name}`" in blocks["frames"]
        for signal in message.signals:
            assert f"| {message.name} | `{signal.name}` |" in blocks["signals"]
    for node in database.nodes:
        assert f"| `{node.name}` |" in blocks["nodes"]


def test_a_change_of_the_dbc_shows_in_the_tables(tmp_path: Path) -> None:
    """The tables come from the DBC file, not from a copy: change a factor, see it."""
    changed = tmp_path / "changed.dbc"
    changed.write_text(DBC_PATH.read_text().replace(
        'SG_ VX : 16|16@1- (0.01,0) [-327.68|327.67] "m/s"', 'SG_ VX : 16|16@1- (0.02,0) [-655.36|655.34] "m/s"'))
    text = contract_tables.render(DOC.read_text(), load_database(changed))
    row = next(line for line in text.splitlines() if line.startswith("| VEH_DYN | `VX` |"))
    print(row)
    assert "| 0.02 |" in row and "-655.36 .. 655.34" in row
    assert contract_tables.stale_tables(DOC, load_database(changed)) == ["signals"]


def test_missing_markers_are_named(tmp_path: Path) -> None:
    text = DOC.read_text().replace("<!-- END GENERATED frames -->", "")
    with pytest.raises(contract_tables.ContractDocError, match="BEGIN GENERATED frames"):
        contract_tables.render(text)


def test_check_command_reports_stale_tables_and_the_fix(tmp_path: Path) -> None:
    doc = tmp_path / "can-contract.md"
    doc.write_text(DOC.read_text().replace("| 0.0001 |", "| 0.0002 |", 1))
    command = [sys.executable, "-m", "can_defs.contract_tables", "--doc", str(doc)]
    check = subprocess.run([*command, "--check"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    print(check.stderr)
    assert check.returncode == 1 and "python -m can_defs.contract_tables" in check.stderr
    assert subprocess.run(command, cwd=ROOT, capture_output=True, timeout=60).returncode == 0
    assert doc.read_text() == DOC.read_text()


def test_the_ecu_help_and_the_code_point_to_the_doc_in_the_repository() -> None:
    assert "docs/can-contract.md" in build_parser().format_help()
    # "../shared/spec/can-contract.md", or a bare "can-contract.md" in prose, which a
    # fresh clone cannot resolve
    outside = re.compile(r"shared/spec/can-contract|(?:^|[\s(`'])can-contract\.md")
    offenders = [f"{path.relative_to(ROOT)}:{number}"
                 for folder in ("can_defs", "models", "controller", "firmware_sim", "hil", "tests")
                 for path in sorted((ROOT / folder).rglob("*.py")) if path != Path(__file__)
                 for number, line in enumerate(path.read_text().splitlines(), start=1)
                 if outside.search(line)]
    assert not offenders, f"point these to docs/can-contract.md: {offenders}"

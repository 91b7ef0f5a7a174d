"""The DBC describes exactly the contract's signal table (tests/data/can_contract.csv, a
machine-readable copy of the contract specification's signal table plus the E2E signals
CRC and CNT, kept by hand and independent of the DBC: the tables of docs/can-contract.md
are generated from the DBC, so they cannot serve as this check)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import cantools
import pytest

from can_defs import DBC_PATH, CtrlMode, FrameId, QpStatus, load_database

CONTRACT_CSV = Path(__file__).parent / "data" / "can_contract.csv"


def _contract_rows() -> list[dict[str, str]]:
    with CONTRACT_CSV.open(newline="") as handle:
        return list(csv.DictReader(handle))


ROWS = _contract_rows()


@pytest.fixture(scope="module")
def database() -> cantools.database.can.Database:
    # strict=True: cantools refuses overlapping signals and signals outside the frame.
    return cantools.database.load_file(str(DBC_PATH), strict=True)


def test_dbc_loads_strict_with_contract_nodes(database):
    nodes = [node.name for node in database.nodes]
    print(f"nodes {nodes}, {len(database.messages)} messages")
    assert nodes == ["ECU", "PLANT", "PLANNER", "MASTER"]
    assert load_database() is load_database(), "the codec must parse the DBC once"


def test_dbc_has_exactly_the_contract_frames(database):
    contract = {(row["frame"], int(row["id"], 16)) for row in ROWS}
    in_dbc = {(message.name, message.frame_id) for message in database.messages}
    print(f"contract frames {sorted(contract, key=lambda f: f[1])}")
    assert in_dbc == contract
    assert {name: fid for name, fid in contract} == {fid.name: int(fid) for fid in FrameId}
    for message in database.messages:
        assert message.length == 8, message.name
        assert not message.is_extended_frame, message.name


def test_dbc_has_exactly_the_contract_signals(database):
    for message in database.messages:
        contract = [row["signal"] for row in ROWS if row["frame"] == message.name]
        print(f"{message.name}: {contract}")
        assert sorted(signal.name for signal in message.signals) == sorted(contract)


def _layout_mismatches(database, row: dict[str, str]) -> list[str]:
    """Every field of one contract row that the DBC does not reproduce."""
    message = database.get_message_by_name(row["frame"])
    signal = message.get_signal_by_name(row["signal"])
    unit = "" if row["unit"] == "-" else row["unit"]
    receivers = sorted(row["receivers"].split())
    period = None if row["period_ms"] == "lockstep" else int(row["period_ms"])
    choices = {}
    if row["choices"]:
        for entry in row["choices"].split(";"):
            value, name = entry.split(" ")
            choices[int(value)] = name
    checks = {
        "id": (message.frame_id, int(row["id"], 16)),
        "byte order": (signal.byte_order, "little_endian"),
        "start bit": (signal.start, int(row["start_bit"])),
        "length": (signal.length, int(row["length"])),
        "signed": (signal.is_signed, {"yes": True, "no": False}[row["signed"]]),
        "factor": (signal.scale, float(row["factor"])),
        "offset": (signal.offset, float(row["offset"])),
        "unit": (signal.unit or "", unit),
        "minimum": (signal.minimum, float(row["minimum"])),
        "maximum": (signal.maximum, float(row["maximum"])),
        "sender": (message.senders, [row["sender"]]),
        "signal receivers": (sorted(signal.receivers), receivers),
        "frame receivers": (sorted(message.receivers), receivers),
        "period": (message.cycle_time, period),
        "choices": ({int(v): str(n) for v, n in (signal.choices or {}).items()}, choices),
    }
    mismatches = []
    for name, (in_dbc, in_contract) in checks.items():
        if isinstance(in_contract, float):
            equal = math.isclose(in_dbc, in_contract, rel_tol=1e-12, abs_tol=1e-12)
        else:
            equal = in_dbc == in_contract
        if not equal:
            mismatches.append(f"{row['frame']}.{row['signal']} {name}: DBC {in_dbc!r}, "
                              f"contract {in_contract!r}")
    return mismatches


def test_signal_layout_matches_contract(database):
    mismatches = []
    for row in ROWS:
        found = _layout_mismatches(database, row)
        print(f"{row['frame']}.{row['signal']}: 15 fields compared, {len(found)} mismatches")
        mismatches += found
    assert len(ROWS) == 35
    assert mismatches == []


def test_contract_range_is_the_representable_range():
    """The contract only says senders saturate to the representable range, so the DBC's
    [min|max] is that range (or the defined choices for CTRL_MODE / QP_STATUS). Checked
    here from length, signedness and factor, independently of the CSV's numbers."""
    for row in ROWS:
        length, factor = int(row["length"]), float(row["factor"])
        if row["signed"] == "yes":
            raw_min, raw_max = -(1 << (length - 1)), (1 << (length - 1)) - 1
        else:
            raw_min, raw_max = 0, (1 << length) - 1
        if row["choices"]:
            values = [int(entry.split(" ")[0]) for entry in row["choices"].split(";")]
            raw_min, raw_max = min(values), max(values)
        print(f"{row['frame']}.{row['signal']}: raw {raw_min}..{raw_max} -> "
              f"{raw_min * factor:g}..{raw_max * factor:g}")
        assert math.isclose(float(row["minimum"]), raw_min * factor, abs_tol=1e-9), row
        assert math.isclose(float(row["maximum"]), raw_max * factor, abs_tol=1e-9), row


def test_e2e_frames_have_crc_and_counter_hil_frames_do_not(database):
    for message in database.messages:
        names = {signal.name for signal in message.signals}
        protected = message.frame_id not in (FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK)
        print(f"{message.name}: E2E {protected}")
        assert ({"CRC", "CNT"} <= names) == protected
        if protected:
            crc, counter = message.get_signal_by_name("CRC"), message.get_signal_by_name("CNT")
            assert (crc.start, crc.length, counter.start, counter.length) == (0, 8, 8, 4)
            # Signals other than CRC/CNT must leave bits 0..11 to the E2E header.
            for signal in message.signals:
                if signal.name not in ("CRC", "CNT"):
                    assert signal.start >= 12, signal.name


def test_choice_names_match_the_python_enums(database):
    ctrl_mode = database.get_message_by_name("STEER_TORQUE_CMD").get_signal_by_name("CTRL_MODE")
    qp_status = database.get_message_by_name("CTRL_DIAG").get_signal_by_name("QP_STATUS")
    print(f"CTRL_MODE {dict(ctrl_mode.choices)}; QP_STATUS {dict(qp_status.choices)}")
    assert {int(v): str(n) for v, n in ctrl_mode.choices.items()} == {m.value: m.name for m in CtrlMode}
    assert {int(v): str(n) for v, n in qp_status.choices.items()} == {m.value: m.name for m in QpStatus}


def test_every_signal_is_commented_and_bus_attributes_set(database):
    uncommented = [f"{m.name}.{s.name}" for m in database.messages for s in m.signals if not s.comment]
    print(f"signals without comment: {uncommented}; baudrate "
          f"{database.dbc.attributes['Baudrate'].value}")
    assert uncommented == []
    assert all(message.comment for message in database.messages)
    assert database.dbc.attributes["Baudrate"].value == 500000


def test_dbc_round_trips_through_cantools_writer(database, tmp_path):
    """A third-party tool re-exporting the DBC keeps every frame and signal."""
    copy = tmp_path / "copy.dbc"
    cantools.database.dump_file(database, str(copy))
    reloaded = cantools.database.load_file(str(copy), strict=True)
    for message in database.messages:
        other = reloaded.get_message_by_frame_id(message.frame_id)
        print(f"{message.name}: {len(other.signals)} signals after re-export")
        assert other.name == message.name and other.cycle_time == message.cycle_time
        for signal in message.signals:
            copied = other.get_signal_by_name(signal.name)
            assert (copied.start, copied.length, copied.is_signed, copied.scale,
                    copied.minimum, copied.maximum) == (
                signal.start, signal.length, signal.is_signed, signal.scale,
                signal.minimum, signal.maximum)


def test_dbc_that_disagrees_with_the_frame_classes_is_refused(tmp_path):
    """The codec cross-checks the DBC against the dataclasses when it builds: a renamed
    signal or choice is a DbcLoadError naming it, not a wrong frame on the bus."""
    from can_defs import DbcLoadError, SteerTorqueCmd, VehDyn
    from can_defs.codec import _FrameCodec

    text = DBC_PATH.read_text()
    cases = {
        "renamed signal": (text.replace("SG_ VY :", "SG_ VY_BODY :"), VehDyn, "VY"),
        "misspelt choice": (text.replace('"SAFE_STOP"', '"SAFESTOP"'), SteerTorqueCmd, "CTRL_MODE"),
    }
    for name, (mutated, frame_class, culprit) in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.dbc"
        path.write_text(mutated)
        message = load_database(path).get_message_by_frame_id(int(frame_class.FRAME_ID))
        with pytest.raises(DbcLoadError, match=culprit) as error:
            _FrameCodec(frame_class, message)
        print(f"{name}: DbcLoadError({error.value})")
    with pytest.raises(DbcLoadError, match="missing.dbc"):
        load_database(tmp_path / "missing.dbc")


def test_interaction_layer_attributes_for_canoe(database):
    """Every frame a standard CAN frame that an interaction layer sends, but the lockstep
    handshakes; QP_STATUS starts at NOT_RUN, every other signal at raw 0."""
    definitions = database.dbc.attribute_definitions

    def attribute(message, name: str) -> str:
        """The message's value of an ENUM attribute by name, its default where not set."""
        definition = definitions[name]
        if name in message.dbc.attributes:
            return definition.choices[message.dbc.attributes[name].value]
        return definition.default_value

    for message in database.messages:
        assert attribute(message, "VFrameFormat") == "StandardCAN", message.name
        handshake = message.name in ("HIL_SYNC", "HIL_SYNC_ACK")
        assert attribute(message, "GenMsgILSupport") == ("No" if handshake else "Yes"), message.name
        for signal in message.signals:
            expected = 15 if (message.name, signal.name) == ("CTRL_DIAG", "QP_STATUS") else 0
            assert (signal.raw_initial or 0) == expected, (message.name, signal.name)

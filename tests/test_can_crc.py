"""CRC-8 SAE J1850 of the E2E protection."""
from __future__ import annotations

from hypothesis import given, strategies as st

from can_defs.crc import crc8_j1850, e2e_crc

from contract_reference import crc8_sae_j1850_bitwise


def test_check_value_over_123456789():
    value = crc8_j1850(b"123456789")
    print(f"CRC-8/SAE-J1850('123456789') = 0x{value:02X} (catalogue: 0x4B)")
    assert value == 0x4B


def test_empty_input_is_init_xor_out():
    print(f"CRC of b'' = 0x{crc8_j1850(b''):02X}")
    assert crc8_j1850(b"") == 0x00  # 0xFF ^ 0xFF


@given(st.binary(max_size=64))
def test_table_matches_bitwise_reference(data):
    assert crc8_j1850(data) == crc8_sae_j1850_bitwise(data)


@given(st.integers(0, 0x7FF), st.binary(min_size=8, max_size=8))
def test_e2e_crc_covers_id_low_high_then_bytes_1_to_7(arbitration_id, payload):
    expected = crc8_sae_j1850_bitwise(bytes([arbitration_id & 0xFF, arbitration_id >> 8]) + payload[1:])
    assert e2e_crc(arbitration_id, payload) == expected


def test_e2e_crc_ignores_byte_0_and_depends_on_the_id():
    payload = bytes(range(8))
    changed_byte0 = bytes([0xAA]) + payload[1:]
    print(f"0x100: 0x{e2e_crc(0x100, payload):02X}, 0x200: 0x{e2e_crc(0x200, payload):02X}")
    assert e2e_crc(0x100, payload) == e2e_crc(0x100, changed_byte0)
    assert e2e_crc(0x100, payload) != e2e_crc(0x200, payload)

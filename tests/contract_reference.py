"""The contract's E2E and bit layout written out independently of ``can_defs``.

Tests use these to check our frames the way a third-party node would read them: straight
from the contract table, one bit at a time, with no project code involved.
"""
from __future__ import annotations


def crc8_sae_j1850_bitwise(data: bytes) -> int:
    """CRC-8/SAE-J1850 one bit at a time (poly 0x1D, init 0xFF, xorout 0xFF, no reflection)."""
    register = 0xFF
    for byte in data:
        register ^= byte
        for _ in range(8):
            register = ((register << 1) ^ 0x1D) & 0xFF if register & 0x80 else (register << 1) & 0xFF
    return register ^ 0xFF


def contract_crc(arbitration_id: int, data: bytes) -> int:
    """Byte 0 of an E2E frame: the CRC over ID low byte, ID high byte, payload bytes 1..7."""
    return crc8_sae_j1850_bitwise(bytes([arbitration_id & 0xFF, arbitration_id >> 8]) + bytes(data[1:8]))


def e2e_ok(arbitration_id: int, data: bytes) -> bool:
    """Whether byte 0 carries the contract's CRC."""
    return data[0] == contract_crc(arbitration_id, data)


def signed(data: bytes, start_bit: int, length: int) -> int:
    """Little-endian two's-complement field of ``length`` bits from ``start_bit``."""
    raw = unsigned(data, start_bit, length)
    return raw - (1 << length) if raw & (1 << (length - 1)) else raw


def unsigned(data: bytes, start_bit: int, length: int) -> int:
    """Little-endian unsigned field of ``length`` bits from ``start_bit``."""
    return (int.from_bytes(data, "little") >> start_bit) & ((1 << length) - 1)

"""CRC-8 SAE J1850 of the E2E protection (docs/can-contract.md, "End-to-end protection").

Parameters: polynomial 0x1D, initial value 0xFF, final XOR 0xFF, no reflection
(CRC-8/SAE-J1850 of the CRC catalogue; check value over ASCII "123456789" is 0x4B).
"""
from __future__ import annotations

from collections.abc import Iterable

CRC8_J1850_POLY = 0x1D
CRC8_J1850_INIT = 0xFF
CRC8_J1850_XOR_OUT = 0xFF


def _build_table(poly: int) -> tuple[int, ...]:
    """CRC of every single byte value with a zero register: one table look-up per byte
    replaces eight shift/XOR steps on the ECU's hot path."""
    table = []
    for byte in range(256):
        register = byte
        for _ in range(8):
            register = ((register << 1) ^ poly) & 0xFF if register & 0x80 else (register << 1) & 0xFF
        table.append(register)
    return tuple(table)


_TABLE = _build_table(CRC8_J1850_POLY)


def crc8_j1850(data: Iterable[int]) -> int:
    """CRC-8 SAE J1850 of `data` (bytes, bytearray or any iterable of 0..255 ints)."""
    register = CRC8_J1850_INIT
    table = _TABLE
    for byte in data:
        register = table[register ^ byte]
    return register ^ CRC8_J1850_XOR_OUT


def e2e_crc(arbitration_id: int, payload: bytes) -> int:
    """CRC of an E2E-protected frame: over the 11-bit identifier as two bytes (low byte
    first, then high byte) followed by payload bytes 1..7 (byte 0 holds the CRC itself).

    `payload` must be 8 bytes long (the caller checks the length).
    """
    register = CRC8_J1850_INIT
    table = _TABLE
    register = table[register ^ (arbitration_id & 0xFF)]
    register = table[register ^ ((arbitration_id >> 8) & 0xFF)]
    for byte in payload[1:8]:
        register = table[register ^ byte]
    return register ^ CRC8_J1850_XOR_OUT

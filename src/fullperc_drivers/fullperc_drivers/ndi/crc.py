"""CRC-16/ARC as used by the NDI Combined API (reference/ndi.md §1.6).

Polynomial x^16 + x^15 + x^2 + 1 (reflected 0xA001), init 0, no final XOR. Commands in the
``CMD:params`` form carry it as 4 uppercase hex digits over every character before the CRC
(including the ``:``); every ASCII reply carries it over its data (embedded LFs included);
binary replies carry it little-endian, once over the 4 header bytes and once over the body.
"""

from __future__ import annotations


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """Running CRC-16/ARC of ``data`` starting from ``crc`` (0 for a fresh CRC)."""
    table = _TABLE
    for b in bytes(data):
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return crc


def crc16_hex(data: bytes | bytearray | str) -> str:
    """The CRC as the device prints it in ASCII: 4 uppercase hex digits."""
    if isinstance(data, str):
        data = data.encode("latin-1")
    return f"{crc16(data):04X}"

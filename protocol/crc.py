"""CRC-32C (Castagnoli, reflected polynomial 0x82F63B78) used for frames and whole transfers.

Parameters (the "CRC-32C/ISCSI" entry of the CRC catalogue): init 0xFFFFFFFF, reflected in and
out, final XOR 0xFFFFFFFF; check value crc32c(b"123456789") == 0xE3069283.
"""
from __future__ import annotations

_POLY_REFLECTED = 0x82F63B78


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ _POLY_REFLECTED if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()


def reference_crc32c_update(crc: int, data: bytes | bytearray | memoryview) -> int:
    """Table-driven CRC-32C, one byte at a time: the reference a firmware port can follow, and the
    oracle the fast path is tested against (about 0.6 us per byte in Python)."""
    table = _TABLE
    value = crc ^ 0xFFFFFFFF
    for byte in bytes(data):
        value = table[(value ^ byte) & 0xFF] ^ (value >> 8)
    return value ^ 0xFFFFFFFF


def _fast_update():
    """google-crc32c's C implementation (SSE4.2 where available), or None when only its pure-Python
    fallback is installed (then the reference is as fast)."""
    try:
        import google_crc32c
    except ImportError:
        return None
    if google_crc32c.implementation != "c":
        return None
    return lambda crc, data: google_crc32c.extend(crc, bytes(data))


crc32c_update = _fast_update() or reference_crc32c_update
crc32c_update.__doc__ = "Continue a CRC-32C over ``data``; start with ``crc=0`` (pre/post inversion is internal)."


def crc32c(data: bytes | bytearray | memoryview) -> int:
    """CRC-32C of ``data`` as an unsigned 32-bit integer."""
    return crc32c_update(0, data)

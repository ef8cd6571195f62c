"""Consistent Overhead Byte Stuffing (Cheshire & Baker 1999): removes every 0x00 from a block.

The encoded block contains no zero byte, so 0x00 can delimit frames on the wire. Overhead is
one byte per started run of 254 non-zero bytes (at most ceil(n/254) + 1 bytes for n bytes).
"""
from __future__ import annotations


class CobsError(ValueError):
    """An encoded block is not valid COBS (zero byte inside, or a code runs past the end)."""


def cobs_max_encoded_len(n: int) -> int:
    """Upper bound of the encoded length of an ``n``-byte block (without delimiter)."""
    return n + n // 254 + 1


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """Encode ``data``; the result contains no 0x00 byte."""
    out = bytearray()
    for segment in bytes(data).split(b"\x00"):
        # Each zero-separated segment becomes runs of <=254 bytes; a full run (code 0xFF)
        # carries no implicit zero, so a segment longer than 254 is split into several codes.
        while len(segment) >= 254:
            out.append(0xFF)
            out += segment[:254]
            segment = segment[254:]
        out.append(len(segment) + 1)
        out += segment
    return bytes(out)


def cobs_decode(block: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS block (delimiter already removed); raises :class:`CobsError`."""
    data = bytes(block)
    if not data:
        raise CobsError("empty block")
    if 0 in data:
        raise CobsError("zero byte inside an encoded block")
    out = bytearray()
    index = 0
    n = len(data)
    while index < n:
        code = data[index]
        end = index + code
        if end > n:
            raise CobsError(f"code {code} at offset {index} runs past the end of a {n}-byte block")
        out += data[index + 1 : end]
        index = end
        if code != 0xFF and index < n:
            out.append(0)
    return bytes(out)

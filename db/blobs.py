"""Pure encoding of numeric arrays into compact, checksummed blobs (and back).

Codec ``shuffle-zlib-v1``: the array is written little-endian, its bytes are regrouped by
significance (all first bytes, then all second bytes, ...: the HDF5/Blosc "shuffle"
filter, which makes the slowly varying high bytes of ADC codes compress well) and
deflated with zlib. The SHA-256 of the stored bytes is kept beside them and checked
before anything is decoded, so a damaged blob is reported, never silently imaged.
"""
from __future__ import annotations

import hashlib
import zlib
from dataclasses import dataclass

import numpy as np

from db.errors import CorruptBlob

CODEC_SHUFFLE_ZLIB_V1 = "shuffle-zlib-v1"
TRACE_DTYPE = "<i2"  # ADC codes
PIXEL_DTYPE = "<f4"  # DI map pixels
SUPPORTED_DTYPES = frozenset({TRACE_DTYPE, PIXEL_DTYPE})
_ZLIB_LEVEL = 1  # 192 kB of shuffled codes: 1.9 ms -> 55 kB at level 1, 10 ms -> 46 kB at level 6 (measured)


@dataclass(frozen=True)
class EncodedArray:
    """Stored bytes of an array with everything needed to decode and verify them."""

    data: bytes
    dtype: str
    shape: tuple[int, ...]
    codec: str
    sha256: str


def checksum(data: bytes) -> str:
    """Hex SHA-256 of the stored bytes."""
    return hashlib.sha256(data).hexdigest()


def _shuffle(raw: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return raw
    grouped = np.frombuffer(raw, dtype=np.uint8).reshape(-1, itemsize)
    return grouped.T.tobytes()


def _unshuffle(shuffled: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return shuffled
    planes = np.frombuffer(shuffled, dtype=np.uint8).reshape(itemsize, -1)
    return planes.T.tobytes()


def encode_array(array: np.ndarray, dtype: str) -> EncodedArray:
    """Encode ``array`` as ``dtype`` (``"<i2"`` or ``"<f4"``); values must already fit it."""
    if dtype not in SUPPORTED_DTYPES:
        raise ValueError(f"unsupported blob dtype {dtype!r}; use one of {sorted(SUPPORTED_DTYPES)}")
    source = np.asarray(array)
    target = np.dtype(dtype)
    if source.dtype.kind != target.kind or source.dtype.itemsize != target.itemsize:
        raise ValueError(f"array has dtype {source.dtype}, expected {target} (convert explicitly)")
    little = np.ascontiguousarray(source, dtype=target)
    data = zlib.compress(_shuffle(little.tobytes(), target.itemsize), _ZLIB_LEVEL)
    return EncodedArray(
        data=data,
        dtype=dtype,
        shape=tuple(int(n) for n in little.shape),
        codec=CODEC_SHUFFLE_ZLIB_V1,
        sha256=checksum(data),
    )


def decode_array(
    data: bytes, *, dtype: str, shape: tuple[int, ...], codec: str, sha256: str
) -> np.ndarray:
    """Verify and decode a blob written by :func:`encode_array`; raises :class:`CorruptBlob`."""
    if codec != CODEC_SHUFFLE_ZLIB_V1:
        raise CorruptBlob(f"unknown blob codec {codec!r}")
    if dtype not in SUPPORTED_DTYPES:
        raise CorruptBlob(f"unknown blob dtype {dtype!r}")
    if any(n < 0 for n in shape):
        raise CorruptBlob(f"negative dimension in blob shape {shape}")
    actual = checksum(bytes(data))
    if actual != sha256:
        raise CorruptBlob(f"blob checksum mismatch: stored sha256 {sha256[:12]}..., data has {actual[:12]}...")
    itemsize = np.dtype(dtype).itemsize
    expected_bytes = int(np.prod(shape, dtype=np.int64)) * itemsize
    inflater = zlib.decompressobj()
    try:
        # max_length bounds the memory a damaged or hostile blob can make us allocate.
        raw = inflater.decompress(bytes(data), expected_bytes + 1)
    except zlib.error as error:
        raise CorruptBlob(f"blob does not inflate: {error}") from error
    if len(raw) != expected_bytes or not inflater.eof or inflater.unused_data:
        raise CorruptBlob(f"blob holds {len(raw)}+ bytes, shape {shape} of {dtype} needs {expected_bytes}")
    values = np.frombuffer(_unshuffle(raw, itemsize), dtype=dtype).reshape(shape)
    return values.astype(values.dtype.newbyteorder("="), copy=True)

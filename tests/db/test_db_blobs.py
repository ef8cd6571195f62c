"""Specification of the blob codec: lossless, compact, and loud about any damage."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from db.blobs import PIXEL_DTYPE, TRACE_DTYPE, decode_array, encode_array
from db.errors import CorruptBlob
from tests.support.db_fixtures import sample_codes

shapes_2d = hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=40)
int16_arrays = hnp.arrays(np.int16, shapes_2d)
float32_arrays = hnp.arrays(np.float32, shapes_2d, elements=st.floats(width=32, allow_nan=True))


def _decode(encoded):
    return decode_array(
        encoded.data, dtype=encoded.dtype, shape=encoded.shape, codec=encoded.codec, sha256=encoded.sha256
    )


@given(int16_arrays)
def test_int16_codes_round_trip_exactly(codes):
    decoded = _decode(encode_array(codes, TRACE_DTYPE))
    assert decoded.dtype == np.int16
    assert decoded.shape == codes.shape
    np.testing.assert_array_equal(decoded, codes)


@given(float32_arrays)
def test_float32_pixels_round_trip_bit_for_bit_including_nan(pixels):
    decoded = _decode(encode_array(pixels, PIXEL_DTYPE))
    assert decoded.dtype == np.float32
    assert decoded.tobytes() == pixels.tobytes()


def test_big_endian_input_decodes_to_the_same_values():
    codes = sample_codes(1, n_channels=2, n_samples=64)
    big = codes.astype(">i2")
    np.testing.assert_array_equal(_decode(encode_array(big, TRACE_DTYPE)), codes)


def test_realistic_traces_are_stored_smaller_than_raw_int16():
    codes = sample_codes(7)
    encoded = encode_array(codes, TRACE_DTYPE)
    assert len(encoded.data) < 0.8 * codes.nbytes


@settings(max_examples=60)
@given(st.data())
def test_any_flipped_bit_is_reported_as_corrupt(data):
    encoded = encode_array(sample_codes(3, n_channels=2, n_samples=256), TRACE_DTYPE)
    bit = data.draw(st.integers(0, len(encoded.data) * 8 - 1))
    damaged = bytearray(encoded.data)
    damaged[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(CorruptBlob, match="checksum"):
        decode_array(bytes(damaged), dtype=encoded.dtype, shape=encoded.shape, codec=encoded.codec, sha256=encoded.sha256)


def test_truncated_blob_is_corrupt():
    encoded = encode_array(sample_codes(4, n_channels=2, n_samples=256), TRACE_DTYPE)
    with pytest.raises(CorruptBlob):
        decode_array(encoded.data[:-5], dtype=encoded.dtype, shape=encoded.shape, codec=encoded.codec, sha256=encoded.sha256)


def test_blob_that_does_not_fill_its_declared_shape_is_corrupt_even_with_a_valid_checksum():
    encoded = encode_array(np.zeros((2, 10), np.int16), TRACE_DTYPE)
    with pytest.raises(CorruptBlob, match="needs"):
        decode_array(encoded.data, dtype=encoded.dtype, shape=(2, 11), codec=encoded.codec, sha256=encoded.sha256)
    with pytest.raises(CorruptBlob, match="needs"):
        decode_array(encoded.data, dtype=encoded.dtype, shape=(2, 9), codec=encoded.codec, sha256=encoded.sha256)


def test_unknown_codec_or_dtype_is_corrupt():
    encoded = encode_array(np.zeros((1, 4), np.int16), TRACE_DTYPE)
    with pytest.raises(CorruptBlob, match="codec"):
        decode_array(encoded.data, dtype=encoded.dtype, shape=encoded.shape, codec="lz4", sha256=encoded.sha256)
    with pytest.raises(CorruptBlob, match="dtype"):
        decode_array(encoded.data, dtype="<i8", shape=encoded.shape, codec=encoded.codec, sha256=encoded.sha256)


def test_encoding_refuses_to_convert_silently():
    with pytest.raises(ValueError, match="expected"):
        encode_array(np.zeros((2, 2), np.float64), TRACE_DTYPE)
    with pytest.raises(ValueError, match="unsupported"):
        encode_array(np.zeros((2, 2), np.int32), "<i4")

"""Specification of the wire layer: CRC-32C, COBS and the streaming frame decoder."""
from __future__ import annotations

import random
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.cobs import CobsError, cobs_decode, cobs_encode, cobs_max_encoded_len
from protocol.crc import crc32c, crc32c_update, reference_crc32c_update
from protocol.framing import (
    MAX_ENCODED_BYTES,
    MAX_PAYLOAD_BYTES,
    Frame,
    FrameCrcError,
    FrameDecoder,
    FrameError,
    FrameTooLong,
    encode_frame,
)

frames = st.builds(
    Frame,
    msg_type=st.integers(0, 255),
    request_id=st.integers(0, 2**32 - 1),
    payload=st.binary(max_size=600),
    flags=st.integers(0, 255),
    seq=st.integers(0, 2**16 - 1),
    version=st.integers(0, 255),
)
small_frames = st.builds(Frame, msg_type=st.integers(0, 255), request_id=st.integers(0, 2**32 - 1),
                         payload=st.binary(max_size=80), seq=st.integers(0, 2**16 - 1))


def only_frames(items):
    return [item for item in items if isinstance(item, Frame)]


@given(st.binary(max_size=3000), st.integers(0, 3000))
def test_crc32c_equals_the_table_driven_reference_split_anywhere(data, cut):
    cut = min(cut, len(data))
    assert crc32c(data) == reference_crc32c_update(0, data)
    assert crc32c_update(crc32c(data[:cut]), data[cut:]) == reference_crc32c_update(0, data)


def test_crc32c_matches_the_catalogue_check_value():
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(b"") == 0
    assert crc32c_update(crc32c(b"12345"), b"6789") == 0xE3069283


@pytest.mark.parametrize(
    "raw, encoded",
    [
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_encodes_the_published_examples(raw, encoded):
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_cobs_decoder_accepts_a_full_final_run_without_trailing_code():
    # Encoders that omit the final 0x01 after a 254-byte run are equally valid.
    assert cobs_decode(b"\xff" + bytes(range(1, 255))) == bytes(range(1, 255))


@given(st.binary(max_size=2000))
def test_cobs_round_trips_and_never_emits_zero(raw):
    encoded = cobs_encode(raw)
    assert 0 not in encoded
    assert len(encoded) <= cobs_max_encoded_len(len(raw))
    assert cobs_decode(encoded) == raw


@pytest.mark.parametrize("bad", [b"", b"\x05\x01", b"\x02\x00"])
def test_cobs_rejects_malformed_blocks(bad):
    with pytest.raises(CobsError):
        cobs_decode(bad)


@given(frames)
def test_frame_round_trips_fed_whole(frame):
    assert FrameDecoder().feed(encode_frame(frame)) == [frame]


@settings(max_examples=30)
@given(small_frames)
def test_frame_round_trips_split_at_every_byte_boundary(frame):
    wire = encode_frame(frame)
    for cut in range(len(wire) + 1):
        decoder = FrameDecoder()
        assert decoder.feed(wire[:cut]) + decoder.feed(wire[cut:]) == [frame]


@given(frames)
def test_frame_round_trips_fed_one_byte_at_a_time(frame):
    decoder = FrameDecoder()
    out = []
    for byte in encode_frame(frame):
        out += decoder.feed(bytes([byte]))
    assert out == [frame]


@given(frames, frames)
def test_two_frames_in_one_buffer_both_decode_in_order(first, second):
    assert FrameDecoder().feed(encode_frame(first) + encode_frame(second)) == [first, second]


@settings(max_examples=25)
@given(small_frames, small_frames, st.integers(1, 255))
def test_every_single_byte_corruption_is_detected(frame, follower, xor):
    wire = encode_frame(frame)
    tail = encode_frame(follower)
    for pos in range(1, len(wire) - 1):  # every byte of the COBS body
        bad = bytearray(wire)
        bad[pos] ^= xor
        out = FrameDecoder().feed(bytes(bad) + tail)
        assert only_frames(out) == [follower], f"corruption at {pos} went undetected"
        assert any(isinstance(item, FrameError) for item in out)


@settings(max_examples=25)
@given(small_frames, small_frames)
def test_every_dropped_byte_is_detected(frame, follower):
    wire = encode_frame(frame)
    tail = encode_frame(follower)
    for pos in range(1, len(wire) - 1):
        out = FrameDecoder().feed(wire[:pos] + wire[pos + 1 :] + tail)
        assert only_frames(out) == [follower], f"dropping byte {pos} went undetected"


@given(small_frames, small_frames)
def test_a_dropped_delimiter_loses_nothing_because_frames_open_with_one(first, second):
    wire = encode_frame(first)
    assert FrameDecoder().feed(wire[:-1] + encode_frame(second)) == [first, second]
    assert FrameDecoder().feed(wire[1:] + encode_frame(second)) == [first, second]


@given(st.lists(st.tuples(small_frames, st.binary(max_size=300)), min_size=1, max_size=5))
def test_garbage_between_frames_is_skipped_and_following_frames_decode(pairs):
    wire = b"".join(garbage + encode_frame(frame) for frame, garbage in pairs)
    assert only_frames(FrameDecoder().feed(wire)) == [frame for frame, _ in pairs]


def test_bad_crc_is_reported_as_a_value_and_later_frames_still_decode():
    good = Frame(msg_type=1, request_id=7, payload=b"abc")
    body = bytearray(cobs_decode(encode_frame(good)[1:-1]))
    body[-6] ^= 0x40  # a payload bit, re-stuffed so that only the CRC can notice
    out = FrameDecoder().feed(b"\x00" + cobs_encode(bytes(body)) + encode_frame(good))
    assert isinstance(out[0], FrameCrcError)
    assert out[-1] == good


def test_over_long_run_is_discarded_once_with_bounded_memory():
    decoder = FrameDecoder()
    errors = []
    for _ in range(10):  # 10 x 1000 non-zero bytes, no delimiter
        errors += decoder.feed(b"\x55" * 1000)
        assert decoder.buffered_bytes <= MAX_ENCODED_BYTES
    assert len(errors) == 1 and isinstance(errors[0], FrameTooLong)
    good = Frame(msg_type=2, request_id=1)
    assert decoder.feed(encode_frame(good)) == [good]


def test_largest_allowed_frame_decodes_and_larger_payload_is_refused():
    big = Frame(msg_type=0x90, request_id=1, payload=bytes(range(1, 256)) * (MAX_PAYLOAD_BYTES // 255)
                + b"\x01" * (MAX_PAYLOAD_BYTES % 255))
    assert FrameDecoder().feed(encode_frame(big)) == [big]
    with pytest.raises(ValueError, match="exceeds"):
        encode_frame(Frame(msg_type=0x90, request_id=1, payload=b"\x01" * (MAX_PAYLOAD_BYTES + 1)))


def test_random_fuzz_never_raises_and_never_grows_without_bound():
    rng = random.Random(20261123)
    decoder = FrameDecoder()
    good = Frame(msg_type=0x85, request_id=99, payload=b"\x00\x01\x02" * 50)
    deadline = time.monotonic() + 3.0
    recovered = 0
    for _ in range(100_000):
        if time.monotonic() > deadline:
            break
        n = rng.choice((1, 7, 64, 700, 5000))
        garbage = bytes(rng.getrandbits(8) if rng.random() < 0.9 else 0 for _ in range(n))
        for item in decoder.feed(garbage):
            assert isinstance(item, (Frame, FrameError))
        assert decoder.buffered_bytes <= MAX_ENCODED_BYTES
        if only_frames(decoder.feed(encode_frame(good))) == [good]:
            recovered += 1
    assert recovered > 10

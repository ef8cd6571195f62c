"""Specification of message payloads and of chunked bulk transfers."""
from __future__ import annotations

import dataclasses
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.bulk import BulkAssembler, BulkError, TransferCrcError, n_chunks_for, split_chunks
from protocol.crc import crc32c
from protocol.framing import Frame, FrameDecoder, encode_frame
from protocol.messages import (
    MAX_CHUNK_LIST,
    MESSAGE_CLASSES,
    AcquireReply,
    BulkChunk,
    ErrorReply,
    InfoReply,
    Message,
    MessageError,
    ReadDiRequest,
    ReadTracesRequest,
    TraceMeta,
    UnknownMessageType,
    decode_message,
)

F32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
_BY_CODE = {"B": st.integers(0, 255), "H": st.integers(0, 2**16 - 1), "I": st.integers(0, 2**32 - 1), "f": F32}
CHUNK_LIST = st.lists(st.integers(0, 2**16 - 1), max_size=40).map(tuple)


def _fixed_strategies(cls: type[Message]) -> list:
    return [_BY_CODE[code] for code in cls._STRUCT.format.lstrip("<")]


def _info_replies():
    def build(fixed, node_id, tx, rx, versions):
        return InfoReply(node_id, *fixed, n_tx=len(tx), n_rx=len(rx), tx_angles_deg=tx, rx_angles_deg=rx,
                         version_min=versions[0], version_max=versions[1])

    fixed = st.tuples(*[_BY_CODE[c] for c in "BBBBIIHHBBBBfIfff"])
    angles = st.lists(F32, max_size=16).map(tuple)
    node_ids = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=4)
    return st.builds(build, fixed, node_ids, angles, angles, st.tuples(_BY_CODE["B"], _BY_CODE["B"]))


SPECIAL = {
    InfoReply: _info_replies(),
    ReadTracesRequest: st.builds(lambda f, c: ReadTracesRequest(*f, chunks=c),
                                 st.tuples(*_fixed_strategies(ReadTracesRequest)), CHUNK_LIST),
    ReadDiRequest: st.builds(ReadDiRequest, _BY_CODE["I"], CHUNK_LIST),
    BulkChunk: st.integers(1, 2**16 - 1).flatmap(
        lambda n: st.builds(BulkChunk, st.integers(0, n - 1), st.just(n), st.binary(max_size=300))),
    ErrorReply: st.builds(ErrorReply, _BY_CODE["H"], _BY_CODE["B"],
                          st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=64)),
}


def strategy_for(cls: type[Message]):
    if cls in SPECIAL:
        return SPECIAL[cls]
    return st.builds(lambda values: cls(*values), st.tuples(*_fixed_strategies(cls)))


any_message = st.one_of([strategy_for(cls) for cls in MESSAGE_CLASSES.values()])


def as_version_1(message: Message) -> Message:
    """What survives a version-1 payload: the fields appended in version 2 are None."""
    if isinstance(message, InfoReply):
        return dataclasses.replace(message, version_min=None, version_max=None)
    n = type(message).V1_FIELDS
    if n is None:
        return message
    names = [f.name for f in dataclasses.fields(message)][n:]
    return dataclasses.replace(message, **dict.fromkeys(names))


def test_every_message_type_has_a_distinct_code():
    assert len(MESSAGE_CLASSES) == 16
    assert all(code == cls.TYPE for code, cls in MESSAGE_CLASSES.items())


@given(any_message)
def test_every_message_round_trips_through_its_payload(message):
    assert decode_message(message.TYPE, message.encode()) == message


@given(any_message)
def test_every_message_round_trips_through_a_version_1_payload_without_the_version_2_fields(message):
    v1 = as_version_1(message)
    assert decode_message(message.TYPE, message.encode(1), 1) == v1
    assert v1.encode(1) == message.encode(1)


@given(any_message)
def test_version_2_keeps_every_version_1_offset_and_only_appends(message):
    assert message.encode(2)[: len(message.encode(1))] == message.encode(1)


@pytest.mark.parametrize("cls, v1_bytes, v2_bytes", [(AcquireReply, 25, 36), (TraceMeta, 50, 65)])
def test_the_messages_version_2_extends_have_the_documented_fixed_lengths(cls, v1_bytes, v2_bytes):
    assert (cls.layout(1).size, cls.layout(2).size) == (v1_bytes, v2_bytes)


def test_a_version_2_message_missing_a_version_2_field_cannot_be_encoded():
    reply = AcquireReply(1, 0, 20.0, 0xFFFF, 6000, 5, 77)
    assert len(reply.encode(1)) == 25
    with pytest.raises(MessageError):
        reply.encode(2)


def test_a_version_1_payload_does_not_decode_as_version_2():
    with pytest.raises(MessageError):
        decode_message(AcquireReply.TYPE, AcquireReply(1, 0, 20.0, 1, 6000, 5, 77).encode(1), 2)


@given(_info_replies(), st.sampled_from([1, 2]))
def test_the_protocol_version_of_an_info_reply_is_read_at_its_fixed_offset_in_every_version(info, version):
    assert InfoReply.announced_version(info.encode(version)) == info.protocol_version


@given(any_message, st.integers(0, 2**32 - 1))
def test_every_message_round_trips_through_a_frame_on_the_wire(message, request_id):
    wire = encode_frame(Frame(msg_type=message.TYPE, request_id=request_id, payload=message.encode()))
    (frame,) = FrameDecoder().feed(wire)
    assert frame.request_id == request_id
    assert decode_message(frame.msg_type, frame.payload) == message


@given(any_message)
def test_truncated_payloads_raise_message_error(message):
    payload = message.encode()
    if isinstance(message, (BulkChunk, ErrorReply)) and len(payload) > 4:
        payload = payload[:3]  # their tails are free-length; only the fixed part can be short
    if not payload:
        return
    with pytest.raises(MessageError):
        decode_message(message.TYPE, payload[:-1])


@given(any_message)
def test_payloads_with_trailing_bytes_raise_message_error(message):
    if isinstance(message, BulkChunk) or (isinstance(message, ErrorReply) and len(message.detail) < 64):
        return  # free-length tails
    with pytest.raises(MessageError):
        decode_message(message.TYPE, message.encode() + b"\x00")


def test_unknown_message_type_is_a_typed_error():
    with pytest.raises(UnknownMessageType):
        decode_message(0x42, b"")


def test_a_field_too_large_for_its_wire_type_raises_message_error():
    with pytest.raises(MessageError):
        ReadTracesRequest(measurement_id=2**32, channel_mask=1, start=0, count=0).encode()
    with pytest.raises(MessageError):
        ReadDiRequest(1, tuple(range(MAX_CHUNK_LIST + 1))).encode()


def test_info_reply_rejects_a_node_id_longer_than_thirty_two_bytes():
    reply = InfoReply("x" * 33, 1, 0, 0, 1, 0, 0, 4096, 2048, 1, 10, 10, 4, 1e6, 6000,
                      400.0, 500.0, 3130.0, 0, 1, (), (0.0,), 1, 2)
    with pytest.raises(MessageError):
        reply.encode()


def test_chunk_with_index_beyond_count_is_rejected():
    with pytest.raises(MessageError):
        BulkChunk.decode(struct.pack("<HH", 3, 3))


@given(st.binary(max_size=5000), st.integers(1, 700), st.randoms(use_true_random=False))
def test_bulk_transfer_reassembles_in_any_order_with_duplicates(data, chunk_bytes, rnd):
    pieces = split_chunks(data, chunk_bytes)
    n = n_chunks_for(len(data), chunk_bytes)
    assert len(pieces) == n
    assembler = BulkAssembler(len(data), chunk_bytes, n, crc32c(data))
    order = list(range(n)) + [i for i in range(n) if rnd.random() < 0.3]
    rnd.shuffle(order)
    for index in order:
        assembler.add(BulkChunk(index, n, pieces[index]))
    assert assembler.missing() == []
    assert assembler.result() == data


def test_bulk_assembler_lists_missing_chunks_and_refuses_partial_results():
    data = bytes(range(256)) * 10
    assembler = BulkAssembler(len(data), 512, 5, crc32c(data))
    for index in (0, 2, 4):
        assembler.add(BulkChunk(index, 5, data[index * 512 : (index + 1) * 512]))
    assert assembler.missing() == [1, 3]
    with pytest.raises(BulkError):
        assembler.result()


def test_bulk_assembler_detects_a_wrong_whole_transfer_crc():
    data = b"\x01\x02" * 600
    assembler = BulkAssembler(len(data), 1000, 2, crc32c(data) ^ 1)
    assembler.add(BulkChunk(0, 2, data[:1000]))
    assembler.add(BulkChunk(1, 2, data[1000:]))
    with pytest.raises(TransferCrcError):
        assembler.result()


def test_bulk_assembler_rejects_chunks_of_the_wrong_length_or_count():
    assembler = BulkAssembler(1500, 1000, 2, 0)
    with pytest.raises(BulkError):
        assembler.add(BulkChunk(1, 2, b"\x00" * 499))
    with pytest.raises(BulkError):
        assembler.add(BulkChunk(0, 3, b"\x00" * 1000))
    with pytest.raises(BulkError):
        BulkAssembler(1500, 1000, 3, 0)

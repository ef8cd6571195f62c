"""Chunked bulk reads (READ_TRACES, READ_DI) of the gateway's node client, verified end to end.

A bulk reply is a *_META frame and its chunks, reassembled by :class:`protocol.bulk.BulkAssembler`;
only lost chunks are asked for again (the whole transfer from a node without CHUNK_RETRANSMIT),
and the whole transfer is checked against its CRC-32C. Every request of a read goes through
:class:`gateway.request_retries.RequestRetries` (same request id on a resend, ERROR BUSY retried);
the chunks asked for again count as its retries.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gateway.node_errors import NodeRebooted, ProtocolMismatch, TransferError
from gateway.request_retries import RequestRetries
from protocol.bulk import BulkAssembler, BulkError, TransferCrcError
from protocol.framing import FLAG_LAST
from protocol.messages import MAX_CHUNK_LIST, BulkChunk, Message


def _collect(requests: RequestRetries, request: Message, meta_type: type, pending: dict[int, BulkChunk],
             timeout_s: float):
    """One request of a bulk read; returns its *_META, chunks into ``pending``. An attempt ends
    at the LAST frame or when no frame came for ``timeout_s`` (lost chunks are asked for later)."""
    meta = None
    for answers in requests.attempts(request, timeout_s):
        for frame, message in answers:
            if isinstance(message, meta_type):
                meta = message
            elif isinstance(message, BulkChunk):
                pending[message.index] = message
            else:
                raise ProtocolMismatch(f"unexpected {type(message).__name__} in a bulk reply")
            if frame.flags & FLAG_LAST:
                break
        if meta is not None:
            return meta
    raise AssertionError("unreachable: attempts ends in NodeTimeout")


def read_bulk(
    requests: RequestRetries, make_request: Callable[[tuple[int, ...]], Message], meta_type: type,
    timeout_s: float, rounds: int, chunk_retransmit: bool,
) -> tuple[Any, bytes, int]:
    """Read a chunked transfer in at most ``rounds`` + 1 requests (``make_request`` of the chunks
    wanted, () for all); re-request only missing chunks (all of them again unless
    ``chunk_retransmit``); verify the whole-transfer CRC. Returns (meta, data, chunks re-requested)."""
    rerequested = 0
    first: Any = None  # the transfer's first meta reply (ReadTracesMeta or ReadDiMeta, both carry boot_id)
    crc_failures = 0
    wanted: tuple[int, ...] = ()
    assembler: BulkAssembler | None = None
    for _round in range(rounds + 1):
        pending: dict[int, BulkChunk] = {}
        meta = _collect(requests, make_request(wanted), meta_type, pending, timeout_s)
        if first is None:
            first = meta
        elif meta.boot_id != first.boot_id:
            raise NodeRebooted(f"node rebooted during the transfer (boot id {first.boot_id} -> {meta.boot_id})")
        elif meta != first:
            raise TransferError(f"the node announced a different transfer: {meta} != {first}")
        if assembler is None:
            try:
                assembler = BulkAssembler(meta.total_bytes, meta.chunk_bytes, meta.n_chunks, meta.transfer_crc32c)
            except BulkError as exc:
                raise ProtocolMismatch(str(exc)) from exc
        for chunk in pending.values():
            try:
                assembler.add(chunk)
            except BulkError:
                requests.channel.frame_errors += 1  # a CRC-valid chunk that does not fit: drop and ask again
        missing = assembler.missing()
        if missing and not chunk_retransmit:
            wanted = ()  # the node sends whole transfers only: read it all again, keep what arrived
            rerequested += len(missing)
            requests.retried += len(missing)
            continue
        if not missing:
            try:
                return meta, assembler.result(), rerequested
            except TransferCrcError as exc:
                crc_failures += 1
                if crc_failures > 1:
                    raise TransferError(f"{exc} (after re-reading the whole transfer)") from exc
                assembler, wanted = None, ()
                requests.retried += meta.n_chunks  # every chunk is read again
                continue
        wanted = tuple(missing[:MAX_CHUNK_LIST])
        rerequested += len(wanted)
        requests.retried += len(wanted)  # chunks sent again count as retries (the metric says so)
    raise TransferError(f"{type(first).__name__}: chunks still missing after {rounds} rounds")

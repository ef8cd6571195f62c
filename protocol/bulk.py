"""Chunked bulk transfers (READ_TRACES, READ_DI): splitting on the node, reassembly on the host.

A transfer is a byte string cut into ``chunk_bytes`` pieces (the last may be shorter), each
sent as a BulkChunk; the *_META frame announces total size, chunk count and a CRC-32C over
the whole byte string, so a reassembled transfer is verified end to end.
"""
from __future__ import annotations

from protocol.crc import crc32c
from protocol.messages import BulkChunk, MessageError


class BulkError(MessageError):
    """A chunk does not fit the announced transfer (index, count or length)."""


class TransferCrcError(BulkError):
    """All chunks arrived but the CRC-32C over the whole transfer does not match."""


def n_chunks_for(total_bytes: int, chunk_bytes: int) -> int:
    """Number of chunks for ``total_bytes`` (0 for an empty transfer)."""
    if chunk_bytes <= 0:
        raise ValueError(f"chunk_bytes must be positive, got {chunk_bytes}")
    return -(-total_bytes // chunk_bytes)


def split_chunks(data: bytes, chunk_bytes: int) -> list[bytes]:
    """The chunks of ``data`` in index order."""
    return [data[i : i + chunk_bytes] for i in range(0, len(data), chunk_bytes)]


class BulkAssembler:
    """Collects the chunks of one announced transfer in any order; duplicates are harmless."""

    def __init__(self, total_bytes: int, chunk_bytes: int, n_chunks: int, transfer_crc32c: int) -> None:
        if chunk_bytes <= 0 or n_chunks != n_chunks_for(total_bytes, chunk_bytes):
            raise BulkError(
                f"inconsistent transfer: {total_bytes} bytes in {n_chunks} chunks of {chunk_bytes}"
            )
        self.total_bytes = total_bytes
        self.chunk_bytes = chunk_bytes
        self.n_chunks = n_chunks
        self.transfer_crc32c = transfer_crc32c
        self._chunks: dict[int, bytes] = {}

    def expected_len(self, index: int) -> int:
        return min(self.chunk_bytes, self.total_bytes - index * self.chunk_bytes)

    def add(self, chunk: BulkChunk) -> None:
        """Store one chunk; raises :class:`BulkError` if it does not belong to this transfer."""
        if chunk.n_chunks != self.n_chunks or not 0 <= chunk.index < self.n_chunks:
            raise BulkError(f"chunk {chunk.index}/{chunk.n_chunks} not in a {self.n_chunks}-chunk transfer")
        if len(chunk.data) != self.expected_len(chunk.index):
            raise BulkError(
                f"chunk {chunk.index} has {len(chunk.data)} bytes, expected {self.expected_len(chunk.index)}"
            )
        self._chunks[chunk.index] = bytes(chunk.data)

    def missing(self) -> list[int]:
        """Indices not yet received, ascending."""
        return [i for i in range(self.n_chunks) if i not in self._chunks]

    @property
    def complete(self) -> bool:
        return len(self._chunks) == self.n_chunks

    def result(self) -> bytes:
        """The whole transfer, verified; raises :class:`BulkError` / :class:`TransferCrcError`."""
        if not self.complete:
            raise BulkError(f"{len(self.missing())} of {self.n_chunks} chunks still missing")
        data = b"".join(self._chunks[i] for i in range(self.n_chunks))
        computed = crc32c(data)
        if computed != self.transfer_crc32c:
            raise TransferCrcError(
                f"transfer CRC-32C 0x{computed:08X} != announced 0x{self.transfer_crc32c:08X}"
            )
        return data

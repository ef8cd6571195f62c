"""The mock node's reply cache by request id: a resent CONFIGURE, ACQUIRE or COMPUTE_DI (same
request id, version, type and payload) is answered with the frames of its first answer instead
of being run again. Bounded: the oldest entry goes first."""
from __future__ import annotations

from collections import OrderedDict

from protocol.framing import Frame

REPLY_CACHE_SIZE = 16


class ReplyCache:
    def __init__(self) -> None:
        self._entries: OrderedDict[int, tuple[int, int, bytes, list[Frame]]] = OrderedDict()

    def get(self, request: Frame, version: int) -> list[Frame] | None:
        """The frames that answered this very request before (None if none did)."""
        cached = self._entries.get(request.request_id)
        if cached is not None and cached[:3] == (version, request.msg_type, request.payload):
            return cached[3]
        return None

    def put(self, request: Frame, version: int, frames: list[Frame]) -> None:
        self._entries[request.request_id] = (version, request.msg_type, request.payload, frames)
        self._entries.move_to_end(request.request_id)
        while len(self._entries) > REPLY_CACHE_SIZE:
            self._entries.popitem(last=False)

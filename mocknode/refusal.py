"""How a command of the mock node refuses: it raises :class:`Refused`, and the node answers the
request with an ERROR reply of that code (``mocknode/node.py``)."""
from __future__ import annotations

from protocol.messages import ErrorCode


class Refused(Exception):
    """Answer the current request with an ERROR reply."""

    def __init__(self, code: ErrorCode, detail: str) -> None:
        super().__init__(detail)
        self.code = code
        self.detail = detail

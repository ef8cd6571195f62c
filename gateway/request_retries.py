"""Bounded retries of the gateway's requests to a node, each under one request id.

A retried command reuses its request id, so the node answers a repeat from its reply cache
instead of running it twice (no double acquisition); ERROR BUSY is retried the same way, after
the same backoff as a timeout. Any other ERROR reply is a :class:`NodeError`; no reply after
every retry, a :class:`NodeTimeout`.
"""
from __future__ import annotations

import random
import time
from collections.abc import Iterator

from gateway.frame_channel import FrameChannel
from gateway.node_errors import NodeError, NodeTimeout, ProtocolMismatch
from protocol.framing import Frame
from protocol.messages import ErrorCode, ErrorReply, Message
from retry_timing.backoff import Backoff


class RequestRetries:
    """Requests over ``channel``: ``retries`` resends after ``backoff`` (jitter from ``rng``)."""

    def __init__(self, channel: FrameChannel, url: str, retries: int, backoff: Backoff, rng: random.Random) -> None:
        self.channel = channel
        self.url = url
        self.retries = retries
        self.backoff = backoff
        self._rng = rng
        # A random first id: a restarted gateway must not hit the node's cache of an old session.
        self._request_id = rng.randrange(1, 2**32)
        self.retried = 0  # commands sent again and chunks asked for again (lost, late or corrupt replies)
        self.busy_replies = 0

    def _next_request_id(self) -> int:
        self._request_id = self._request_id % (2**32 - 1) + 1  # never 0
        return self._request_id

    def _backoff(self, attempt: int) -> None:
        time.sleep(self.backoff.delay_s(attempt, self._rng))

    def attempts(self, request: Message, wait_s: float) -> Iterator[Iterator[tuple[Frame, Message]]]:
        """Send ``request`` and yield, per attempt, an iterator over its replies; resend it with the
        SAME request id (after a backoff) when the caller asks for the next attempt, i.e. after a
        timeout or an ERROR BUSY, until the retries run out (NodeTimeout)."""
        request_id = self._next_request_id()
        busy_before = self.busy_replies
        for attempt in range(self.retries + 1):
            if attempt:
                self.retried += 1
                self._backoff(attempt)
            self.channel.send(request, request_id)
            yield self._answers(request_id, wait_s)
        busy = self.busy_replies - busy_before
        outcome = f"BUSY {busy} times, no reply the other {self.retries + 1 - busy}" if busy else "no reply"
        raise NodeTimeout(
            f"{type(request).__name__} to {self.url}: {outcome} in {self.retries + 1} attempts of {wait_s:.2f} s"
        )

    def _answers(self, request_id: int, wait_s: float) -> Iterator[tuple[Frame, Message]]:
        """The replies to one attempt; ends at a timeout or an ERROR BUSY; any other ERROR is a NodeError."""
        for frame, message in self.channel.replies(request_id, wait_s):
            if isinstance(message, ErrorReply):
                if message.code == ErrorCode.BUSY:
                    self.busy_replies += 1
                    return  # asked again after the backoff, like a timeout
                raise NodeError(message.code, message.detail, message.request_type)
            yield frame, message

    def command(self, request: Message, reply_type: type, wait_s: float):
        """Send ``request`` until its reply arrives (see ``attempts``)."""
        for answers in self.attempts(request, wait_s):
            for _frame, message in answers:
                if isinstance(message, reply_type):
                    return message
                raise ProtocolMismatch(f"expected {reply_type.__name__}, got {type(message).__name__}")
        raise AssertionError("unreachable: attempts ends in NodeTimeout")

"""Typed errors of alert delivery, raised by the sink transports where the fault is found."""
from __future__ import annotations


class AlertError(Exception):
    """Base class of every error raised by ``alerts``."""


class DeliveryFailed(AlertError):
    """One attempt failed (timeout, refused connection, non-2xx, no PUBACK); it may be retried.

    ``retry_after_s`` is the receiver's own ``Retry-After`` when it sent one.
    """

    def __init__(self, message: str, *, retry_after_s: float | None = None) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class EndpointGone(AlertError):
    """The receiver answered 410 Gone: per Standard Webhooks the endpoint is disabled, not retried."""

    def __init__(self, message: str, *, status_code: int = 410) -> None:
        super().__init__(message)
        self.status_code = status_code

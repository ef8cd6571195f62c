"""The errors of talking to a node through the gateway's client (:mod:`gateway.node_client`).

Every one is a :class:`nodelink.transport.NodeLinkError`, as is the transport's own
:class:`~nodelink.transport.PortVanished` (the port itself is gone).
"""
from __future__ import annotations

from nodelink.transport import NodeLinkError
from protocol.messages import ErrorCode

NodeClientError = NodeLinkError  # the base of every error below (and of PortVanished)


class NodeTimeout(NodeClientError):
    """The node did not answer within the timeout, after every retry."""


class ProtocolMismatch(NodeClientError):
    """The node speaks another protocol version, or sent a CRC-valid frame we cannot parse."""


class NodeError(NodeClientError):
    """The node answered with an ERROR reply; ``code`` is an :class:`ErrorCode` (or raw int)."""

    def __init__(self, code: int, detail: str, request_type: int) -> None:
        try:
            self.code: ErrorCode | int = ErrorCode(code)
        except ValueError:
            self.code = code
        self.detail = detail
        self.request_type = request_type
        name = self.code.name if isinstance(self.code, ErrorCode) else str(code)
        super().__init__(f"node error {name} on request 0x{request_type:02X}: {detail}")


class CapabilityMissing(NodeClientError):
    """The command needs a capability the node's INFO does not announce; nothing was sent."""


class NodeRebooted(NodeClientError):
    """The node's boot id changed during a transfer: its RAM (measurements, DI maps) is gone."""


class TransferError(NodeClientError):
    """A bulk transfer could not be completed and verified (CRC-32C) within the retries."""

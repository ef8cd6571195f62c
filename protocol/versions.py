"""Protocol versions and their negotiation (docs/protocol.md, section 3.1), pure.

Version 2 extends version 1: every version-1 field keeps its offset and meaning; ACQUIRE_REPLY,
TRACE_META and INFO_REPLY gain fields at their end. A node may speak several versions and
answers each request in the version of its header; INFO tells the host which one to use.
"""
from __future__ import annotations

PROTOCOL_VERSION = 2  # the newest version this code speaks
OLDEST_VERSION = 1  # the oldest version this code still speaks
SUPPORTED_VERSIONS = range(OLDEST_VERSION, PROTOCOL_VERSION + 1)
# INFO is sent with this header version: every node since version 1 reads it.
HELLO_VERSION = OLDEST_VERSION


def common_version(host_min: int, host_max: int, node_min: int, node_max: int) -> int | None:
    """The version a host and a node talk in: the newest both speak, or None if they share none."""
    best = min(host_max, node_max)
    return best if best >= max(host_min, node_min) else None

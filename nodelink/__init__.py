"""The byte link to a node: a pyserial port opened from a URL. Below the gateway and the
conformance checker, which both talk to nodes through it; knows bytes, not messages."""

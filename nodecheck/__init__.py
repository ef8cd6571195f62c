"""``pipesentry node-check``: the numbered requirements of docs/protocol.md run against a node.

Below the gateway: it talks to the node through ``nodelink`` with the ``protocol`` codec,
byte by byte where a requirement is about bytes, and never uses the gateway's client.
"""

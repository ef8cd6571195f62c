"""The gateway's uplink: store-and-forward of its records to a central PipeSentry (docs/gateway.md, "Uplink").

``records`` makes queue rows into the wire contract's records, ``batches`` decides what one
batch holds and what the centre's answer means (pure), ``sender`` is the thread that sends.
The queue itself is ``db.uplink_queue``.
"""

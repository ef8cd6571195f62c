"""Wire efficiency of a full READ_TRACES transfer (8 channels x 6000 int16 samples), measured by encoding it.

Run: ``.venv/bin/python bench/bench_wire.py [--pty]``. ``--pty`` also times a real transfer
from the mock node paced at 230400 baud over a pseudo-terminal.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gateway.node_client import NodeClient
from mocknode.node import MockNode
from mocknode.scenario import default_scenario
from mocknode.server import MockNodeServer
from protocol.framing import Frame, FrameDecoder, encode_frame
from protocol.messages import AcquireRequest, ComputeDiRequest, ReadDiRequest, ReadTracesRequest

BAUD = 230400
LINE_BYTES_PER_S = BAUD / 10  # 8N1: start + 8 data + stop bits


def eight_channel_scenario():
    base = default_scenario(1).nodes[0]
    rings = base.rings.model_copy(update={"n_transducers": 8})
    acquisition = base.acquisition.model_copy(update={"n_samples": 6000})
    return base.model_copy(update={"rings": rings, "acquisition": acquisition})


def wire_of(node: MockNode, message, request_id: int) -> tuple[bytes, bytes]:
    request = encode_frame(Frame(message.TYPE, request_id, message.encode()))
    reply = b"".join(encode_frame(f) for f in node.handle(Frame(message.TYPE, request_id, message.encode())))
    return request, reply


def report(name: str, payload_bytes: int, request: bytes, reply: bytes) -> None:
    efficiency = payload_bytes / len(reply)
    print(f"{name}:")
    print(f"  payload bytes              {payload_bytes}")
    print(f"  wire bytes node->host      {len(reply)}  (request host->node {len(request)})")
    print(f"  wire efficiency            {100 * efficiency:.2f} %  (target >= 95 %)")
    print(f"  time at {BAUD} 8N1       {len(reply) / LINE_BYTES_PER_S:.3f} s")
    print(f"  line-rate limit            {payload_bytes / LINE_BYTES_PER_S:.3f} s at {LINE_BYTES_PER_S:.0f} B/s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pty", action="store_true", help="also time a paced transfer over a pseudo-terminal")
    args = parser.parse_args()

    scenario = eight_channel_scenario()
    node = MockNode(scenario)
    node.handle(Frame(AcquireRequest.TYPE, 1, AcquireRequest(1).encode()))
    node.handle(Frame(AcquireRequest.TYPE, 2, AcquireRequest(0).encode()))
    request, reply = wire_of(node, ReadTracesRequest(2, 0xFF, 0, 0), 3)
    report("READ_TRACES 8 ch x 6000 int16", 8 * 6000 * 2, request, reply)

    started = time.perf_counter()
    frames = FrameDecoder().feed(reply)
    decode_s = time.perf_counter() - started
    print(f"  host decode (Python)       {1e3 * decode_s:.1f} ms for {len(frames)} frames")

    node.handle(Frame(ComputeDiRequest.TYPE, 4, ComputeDiRequest(2).encode()))
    request, reply = wire_of(node, ReadDiRequest(1), 5)
    report("READ_DI 201 x 180 float32 (default on-board grid)", 201 * 180 * 4, request, reply)

    if args.pty:
        with MockNodeServer([scenario], kind="pty", pace=True, baud=BAUD) as server:
            with NodeClient(server.urls[scenario.node_id], timeout_s=1.0) as client:
                measurement = client.acquire(baseline=False)
                started = time.monotonic()
                transfer = client.read_traces(measurement.measurement_id)
                elapsed_s = time.monotonic() - started
        print("paced READ_TRACES over a pseudo-terminal:")
        print(f"  measured                   {elapsed_s:.3f} s for {transfer.codes.nbytes} payload bytes"
              f" ({transfer.codes.nbytes / elapsed_s:.0f} B/s, {100 * transfer.codes.nbytes / elapsed_s / LINE_BYTES_PER_S:.1f} % of line rate)")


if __name__ == "__main__":
    main()

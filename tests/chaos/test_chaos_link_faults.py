"""Chaos on the serial link: every byte of a frame corrupted in turn, and a fleet where good nodes share
the gateway with a node that stalls, one that reboots, one of another protocol version, one that sends
nothing but garbage and one whose cable is pulled mid-frame and plugged back (the port reappears under
another name). What must hold: no corrupted frame is ever accepted and the next good one always is;
nothing a bad node sends is stored as a measurement; every stored record decodes whole, none twice;
the good nodes keep polling (their cadence is printed beside the bad nodes')."""
from __future__ import annotations

import itertools
import statistics
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select, text

from db.database import open_database
from db.measurements import load_traces
from db.models import MeasurementRow
from gateway.config import load_settings
from gateway.daemon import Gateway
from mocknode.faults import FaultSpec
from mocknode.scenario import default_scenario
from mocknode.server import MockNodeServer
from protocol.framing import Frame, FrameDecoder, FrameError, encode_frame
from tests.support.chaos import Counts, size
from tests.support.process_harness import gateway_config, gateway_node, wait_until

GOOD = ["good-1", "good-2"]
BAD = {
    "stalls": FaultSpec(stall_probability=0.5, stall_s=1.5),
    "reboots": FaultSpec(reboot_every_s=1.5, reboot_probability=0.02),
    "future-version": FaultSpec(protocol_version=3),
    "garbage": FaultSpec(corrupt_byte_rate=1.0),
    "cable": FaultSpec(disconnect_every_s=2.0, reconnect_after_s=0.5),
}
NEVER_STORED = ("future-version", "garbage")  # nothing of theirs can pass a CRC or the version check


def test_every_byte_of_a_frame_corrupted_in_turn_is_rejected_and_the_next_frame_accepted():
    counts = Counts("frame byte corruption")
    good = Frame(msg_type=0x81, request_id=0xA5A5_0001, payload=bytes(range(256)) * 4, flags=0x80, seq=7)
    wire = encode_frame(good)
    follower = encode_frame(Frame(msg_type=0x82, request_id=2, payload=b"next", flags=0x80))
    decoder = FrameDecoder()
    for position in range(len(wire)):
        for mask in (0x01, 0x80, 0xFF):  # the lowest bit, the highest, every bit of the byte
            damaged = bytearray(wire)
            damaged[position] ^= mask
            counts.faults += 1
            out = decoder.feed(bytes(damaged) + follower)
            frames = [f for f in out if isinstance(f, Frame)]
            counts.checked += len(frames)
            counts.corrupted += sum(1 for f in frames if f not in (good, Frame(0x82, 2, b"next", 0x80)))
            counts.lost += 0 if frames and frames[-1].payload == b"next" else 1  # the next good frame got through
            counts.duplicated += max(0, sum(1 for f in frames if f.payload == b"next") - 1)
            assert all(isinstance(f, Frame | FrameError) for f in out)
        decoder.feed(b"\x00")  # line idle between rounds
    counts.report(frame_bytes=len(wire))
    counts.assert_nothing_lost()


@pytest.mark.e2e  # the gateway's threads polling mock nodes on pseudo-terminals
@pytest.mark.timeout(300)
def test_bad_nodes_never_store_garbage_and_the_good_nodes_keep_polling(tmp_path: Path):
    counts = Counts("link faults")
    template = default_scenario(1).nodes[0]
    scenarios = [template.model_copy(update={"node_id": n, "seed": 60 + i}) for i, n in enumerate(GOOD)]
    scenarios += [template.model_copy(update={"node_id": n, "seed": 70 + i, "faults": f})
                  for i, (n, f) in enumerate(BAD.items())]
    links = tmp_path / "links"
    enough = size(6, 60)
    with MockNodeServer(scenarios, link_dir=links):
        config = tmp_path / "gateway.toml"
        nodes = [gateway_node(n, links, interval_s=0.2) for n in [*GOOD, *BAD]]
        config.write_text(gateway_config(tmp_path / "g.db", nodes, reopen_backoff_max_s=1.0))
        settings = load_settings(config)
        database = open_database(settings.database.url)
        gateway = Gateway(settings, database)
        gateway.start()
        try:
            wait_until(lambda: all(n >= enough for n in _per_node(database, GOOD).values())
                       and _per_node(database, ["cable"])["cable"] >= 2, 240, 0.2,
                       what=f"{enough} measurements of each good node and the cable node back twice")
        finally:
            gateway.shutdown(settings.shutdown_timeout_s)
        counters = {w.settings.id: w.counters for w in gateway.workers}
    counts.faults = sum(c.failures + c.port_reopens for n, c in counters.items() if n in BAD)
    with database.session() as session:
        assert session.execute(text("PRAGMA integrity_check")).scalar_one() == "ok"
        rows = session.scalars(select(MeasurementRow).order_by(MeasurementRow.id)).all()
        counts.checked = len(rows)
        keys = [(r.node_id, r.boot_id, r.node_measurement_id) for r in rows]
        counts.duplicated = len(keys) - len(set(keys))
        for row in rows:
            traces = load_traces(row)
            if traces.ndim != 2 or not np.all(np.isfinite(traces)):
                counts.corrupted += 1
        stored = {n: sum(1 for r in rows if r.node_id == n) for n in [*GOOD, *BAD]}
        cadence = {n: _median_gap_s([r.acquired_at for r in rows if r.node_id == n]) for n in [*GOOD, *BAD]}
    database.dispose()
    for name in NEVER_STORED:
        assert stored[name] == 0, f"{name} had {stored[name]} measurements stored"
    counts.corrupted += sum(stored[n] for n in NEVER_STORED)
    counts.report(stored=stored, median_gap_s=cadence,
                  bad_node_failures={n: (counters[n].failures, counters[n].port_reopens) for n in BAD})
    counts.assert_nothing_lost()


def _per_node(database, names: list[str]) -> dict[str, int]:
    with database.session() as session:
        rows = session.execute(select(MeasurementRow.node_id).where(MeasurementRow.node_id.in_(names))).scalars()
        found = list(rows)
    return {n: found.count(n) for n in names}


def _median_gap_s(times) -> str:
    if len(times) < 2:
        return "-"
    return f"{statistics.median((b - a).total_seconds() for a, b in itertools.pairwise(times)):.2f}"

"""Store-and-forward across a broken link (issue 17, "Done when"): a central service on 127.0.0.1 against
PostgreSQL (its own database, created and dropped here) and two gateway processes, each with its own
mock nodes, reporting to it through a link-breaking proxy each.

The link is broken three ways while the nodes keep being measured: the central service is stopped
and started again; the proxy drops connections mid-request (before the centre stored the batch,
and after it stored it but before the gateway heard); and one gateway is killed with SIGKILL while
the centre's answer to its upload is held back, then started again. Afterwards the centre holds
exactly the edges' records: the same measurements per node in the same order with the same
checksums, the same detections, state changes, baselines and alert events, nothing twice.
"""
from __future__ import annotations

import hashlib
import os
import signal
import socket
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import httpx
import psycopg
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, undefer

from db.database import Database, open_database
from db.models import (
    BaselineRow,
    DetectionRow,
    EventRow,
    MeasurementRow,
    NodeRow,
    Role,
    StateChangeRow,
)
from db.uplink_queue import queue_stats
from tests.support.db_fixtures import PG_ADMIN_CONNINFO, PG_PORT
from tests.support.metrics_text import sample, total
from tests.support.process_harness import (
    PYTHON,
    Proc,
    gateway_config,
    gateway_metrics_port,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)
from tests.support.tcp_proxy import LinkProxy

pytestmark = [pytest.mark.e2e, pytest.mark.postgres, pytest.mark.timeout(300)]

PHASE_TIMEOUT_S = 90.0
NEW_PER_PHASE = 2  # measurements every node takes while the link is broken, at least


@dataclass
class Edge:
    """One gateway: its mock nodes, its database, its proxy to the centre, its process."""

    name: str
    site: str
    nodes: list[str]
    run_dir: Path
    proxy: LinkProxy
    key: str
    mock: Proc | None = None
    gateway: Proc | None = None
    starts: int = 0

    @property
    def db_url(self) -> str:
        return f"sqlite:///{self.run_dir / 'gateway.db'}"

    def start(self, ready_lag_s: float) -> None:
        links = self.run_dir / "links"
        if self.mock is None:
            scenario = self.run_dir / "scenario.toml"
            scenario.write_text("".join(scenario_node(n, 500 + i) for i, n in enumerate(self.nodes)))
            self.mock = start_mock_nodes(scenario, links, self.run_dir)
            wait_for_links(links, self.nodes, self.mock)
        config = self.run_dir / "gateway.toml"
        config.write_text(gateway_config(
            self.run_dir / "gateway.db", [gateway_node(n, links, interval_s=0.3) for n in self.nodes],
            uplink={"url": self.proxy.url, "key": self.key, "gateway_id": self.name, "site": self.site,
                    "batch_records": 20, "timeout_s": 10.0, "idle_s": 0.2, "backoff_base_s": 0.2,
                    "backoff_cap_s": 1.0, "retry_after_max_s": 2.0, "ready_lag_s": ready_lag_s},
        ))
        self.starts += 1
        self.gateway = start_gateway(config, self.run_dir, name=f"gateway-{self.starts}")

    def measurements(self) -> dict[str, int]:
        return _counts(self.db_url)

    def queue_depth(self) -> int:
        with _reading(self.db_url) as session:
            return queue_stats(session).depth

    def baseline_events(self) -> set[str]:
        """The nodes with a baseline_changed event in this edge's outbox."""
        with _reading(self.db_url) as session:
            return set(session.scalars(select(EventRow.node_id).where(EventRow.kind == "baseline_changed")))

    def cycle_failures(self) -> dict[str, float]:
        """Per node, the cycles (or port openings) that stored no measurement, whatever the cause."""
        metrics = self.scrape("/metrics").text
        return {node: total(metrics, "pipesentry_gateway_node_cycle_failures_total", node=node) for node in self.nodes}

    def scrape(self, path: str) -> httpx.Response:
        assert self.gateway is not None
        port = gateway_metrics_port(self.gateway)
        return httpx.get(f"http://127.0.0.1:{port}{path}", timeout=5.0)

    def close(self) -> None:
        for proc in (self.gateway, self.mock):
            if proc is not None:
                proc.close()


@contextmanager
def _reading(url: str) -> Iterator[Session]:
    """A session on the database at ``url`` (already migrated), its engine disposed afterwards."""
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            yield session
    finally:
        database.dispose()


def _counts(url: str) -> dict[str, int]:
    with _reading(url) as session:
        return dict(session.execute(
            select(MeasurementRow.node_id, func.count()).group_by(MeasurementRow.node_id)).all())


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def central_url() -> Iterator[str]:
    """A PostgreSQL database of its own, migrated, dropped afterwards."""
    try:
        admin = psycopg.connect(PG_ADMIN_CONNINFO, autocommit=True)
    except psycopg.OperationalError as error:
        if os.environ.get("CI") == "true":
            pytest.fail(f"PostgreSQL is required with CI=true: {error}")
        pytest.skip(f"PostgreSQL unreachable: {str(error).strip().splitlines()[0]}")
    name = f"uplink_e2e_{uuid.uuid4().hex[:12]}"
    with admin:
        admin.execute(f'CREATE DATABASE "{name}"')
        try:
            url = f"postgresql+psycopg://postgres@127.0.0.1:{PG_PORT}/{name}"
            open_database(url).dispose()  # migrated to head
            yield url
        finally:
            admin.execute(f'DROP DATABASE "{name}" WITH (FORCE)')


def gateway_key(url: str, site: str) -> str:
    """A key of role gateway for ``site`` (what ``pipesentry apikey create --role gateway --site`` makes)."""
    from db.api_keys import create_api_key

    database = open_database(url, upgrade=False)
    try:
        with database.write() as session:
            _row, token = create_api_key(session, name=f"gateway {site}", role=Role("gateway"), site=site)
    finally:
        database.dispose()
    return token


class Centre:
    def __init__(self, url: str, run_dir: Path) -> None:
        self.url = url
        self.run_dir = run_dir
        self.port = _free_port()
        self.proc: Proc | None = None
        self.starts = 0

    def start(self) -> None:
        self.starts += 1
        self.proc = Proc([PYTHON, "-m", "pipesentry", "api", "--database-url", self.url, "--host", "127.0.0.1",
                          "--port", str(self.port)], self.run_dir, f"centre-{self.starts}")
        wait_until(self._ready, 60, 0.2, what="the central service's /readyz")

    def _ready(self) -> bool:
        assert self.proc is not None and self.proc.alive(), self.proc.stderr[-2000:] if self.proc else ""
        return httpx.get(f"http://127.0.0.1:{self.port}/readyz", timeout=2.0).status_code == 200

    def stop(self) -> None:
        assert self.proc is not None
        # uvicorn shuts down cleanly, then re-raises the SIGTERM it handled
        assert self.proc.terminate(timeout_s=15) in (0, -signal.SIGTERM), self.proc.stderr[-2000:]
        self.proc.close()

    def measurements(self) -> dict[str, int]:
        return _counts(self.url)


def until_each_node_has_more(edges: list[Edge], before: dict[str, int], what: str) -> None:
    def more() -> bool:
        now = {n: c for edge in edges for n, c in edge.measurements().items()}
        return all(now.get(node, 0) >= before.get(node, 0) + NEW_PER_PHASE for edge in edges for node in edge.nodes)

    wait_until(more, PHASE_TIMEOUT_S, 0.3, what=what)


def edge_counts(edges: list[Edge]) -> dict[str, int]:
    return {n: c for edge in edges for n, c in edge.measurements().items()}


def test_the_centre_ends_with_exactly_the_edges_records_whatever_the_link_did(tmp_path, central_url):
    centre = Centre(central_url, tmp_path)
    centre.start()
    edges = []
    for name, site, nodes in (("gw-north", "north", ["north-1", "north-2"]), ("gw-south", "south", ["south-1"])):
        run_dir = tmp_path / name
        run_dir.mkdir()
        edges.append(Edge(name, site, nodes, run_dir, LinkProxy(centre.port), gateway_key(central_url, site)))
    north, south = edges
    try:
        north.start(ready_lag_s=3600)
        south.start(ready_lag_s=1.0)
        wait_until(lambda: all(centre.measurements().get(n, 0) >= 1 for e in edges for n in e.nodes),
                   PHASE_TIMEOUT_S, 0.5, what="the first measurements of every node at the centre")

        # 1. The central service stops: the edges measure on, queue, and say so; then it is back.
        centre.stop()
        outage_from = datetime.now().astimezone()
        until_each_node_has_more(edges, edge_counts(edges), "measurements while the centre is down")
        wait_until(lambda: south.scrape("/readyz").status_code == 503, PHASE_TIMEOUT_S, 0.3,
                   what="south's readiness to fail on its uplink lag")
        readiness = south.scrape("/readyz").json()
        assert readiness["uplink"]["queue_depth"] > 0 and "uplink" in readiness["reasons"][0]
        metrics = north.scrape("/metrics").text
        assert sample(metrics, "pipesentry_gateway_uplink_queue_depth") > 0
        assert sample(metrics, "pipesentry_gateway_uplink_lag_seconds") > 0
        assert sample(metrics, "pipesentry_gateway_uplink_failures_total") > 0
        outage_to = datetime.now().astimezone()
        centre.start()

        # 2. South's link drops connections mid-request, before and after the centre stored the batch;
        # meanwhile north is SIGKILLed while the centre's answer to its upload (stored) is held back.
        before = edge_counts(edges)
        south.proxy.set_mode("drop")
        north.proxy.set_mode("hold")
        north.proxy.wait_for("held", 1, PHASE_TIMEOUT_S)
        assert north.gateway is not None
        os.kill(north.gateway.popen.pid, signal.SIGKILL)
        north.gateway.popen.wait(10)
        north.proxy.set_mode("pass")
        north.start(ready_lag_s=3600)
        south.proxy.wait_for("dropped", 2, PHASE_TIMEOUT_S)  # one of each kind
        until_each_node_has_more(edges, before, "measurements while the links break")
        south.proxy.set_mode("pass")
        wait_until(lambda: sample(north.scrape("/metrics").text, "pipesentry_gateway_uplink_duplicates_total") >= 1,
                   PHASE_TIMEOUT_S, 0.3, what="the restarted gateway re-sending what the centre already stored")

        # The edges' watchers raise baseline_changed up to 30 s after the baseline (offline_after_s / 10):
        # every node's is in its edge's outbox before the queues are drained, or it could come after.
        for edge in edges:
            wait_until(lambda e=edge: e.baseline_events() == set(e.nodes), PHASE_TIMEOUT_S, 0.5,
                       what=f"{edge.name}'s baseline_changed events")

        # The nodes go quiet; every queue drains; the gateways stop. A node's cycles run one after
        # another: once one has failed since its node went quiet, a record it was still fetching is
        # stored, and the queue cannot fill again behind the drain (it did: one record short).
        failed = {edge.name: edge.cycle_failures() for edge in edges}
        for edge in edges:
            assert edge.mock is not None
            edge.mock.close()
        for edge in edges:
            wait_until(lambda e=edge: all(e.cycle_failures()[n] > failed[e.name][n] for n in e.nodes),
                       PHASE_TIMEOUT_S, 0.3, what=f"{edge.name}'s nodes to be found gone")
            wait_until(lambda e=edge: e.queue_depth() == 0, PHASE_TIMEOUT_S, 0.3, what=f"{edge.name}'s queue to drain")
        ready = south.scrape("/readyz")  # caught up: ready again
        assert ready.status_code == 200 and ready.json()["uplink"]["queue_depth"] == 0, ready.text
        for edge in edges:
            assert edge.gateway is not None and edge.gateway.terminate(timeout_s=15) == 0, edge.gateway.stderr[-3000:]
        assert "Traceback" not in north.gateway.stderr + south.gateway.stderr
    finally:
        for edge in edges:
            edge.close()
            edge.proxy.close()
        if centre.proc is not None:
            centre.proc.close()

    central = open_database(central_url, upgrade=False)
    try:
        for edge in edges:
            local = open_database(edge.db_url, upgrade=False)
            try:
                assert_centre_holds_exactly(local, central, edge)
                assert_measured_throughout(local, edge, outage_from, outage_to)
            finally:
                local.dispose()
    finally:
        central.dispose()


def _history(database: Database, node_id: str, *, with_blobs: bool) -> dict[str, list]:
    with database.session() as s:
        measurements = s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == node_id)
                                 .options(undefer(MeasurementRow.traces_blob)).order_by(MeasurementRow.id)).all()
        return {
            "measurements": [(m.kind.value, m.node_measurement_id, m.acquired_at, m.traces_sha256,
                              hashlib.sha256(m.traces_blob or b"").hexdigest() if with_blobs else None)
                             for m in measurements],
            "detections": [(d.state.value, d.peak_di, d.threshold, d.created_at) for d in s.scalars(
                select(DetectionRow).where(DetectionRow.node_id == node_id).order_by(DetectionRow.id))],
            "state_changes": [(c.from_state.value, c.to_state.value, c.at) for c in s.scalars(
                select(StateChangeRow).where(StateChangeRow.node_id == node_id).order_by(StateChangeRow.id))],
            "baselines": [(b.created_at, b.reason) for b in s.scalars(
                select(BaselineRow).where(BaselineRow.node_id == node_id).order_by(BaselineRow.id))],
            "events": [(e.id, e.kind) for e in s.scalars(
                select(EventRow).where(EventRow.node_id == node_id).order_by(EventRow.created_at, EventRow.id))],
        }


def assert_centre_holds_exactly(local: Database, central: Database, edge: Edge) -> None:
    for node_id in edge.nodes:
        here = _history(local, node_id, with_blobs=True)
        there = _history(central, node_id, with_blobs=True)
        assert len(here["measurements"]) >= 3 * NEW_PER_PHASE
        for part in here:  # same counts, same checksums (stored and recomputed), same order, nothing twice
            assert there[part] == here[part], f"{edge.name} {node_id}: the centre's {part} differ"
        assert all(m[3] == m[4] for m in there["measurements"])  # the centre's blobs match their checksums
        with central.session() as s:
            node = s.get(NodeRow, node_id)
            assert node is not None and (node.site, node.gateway_id) == (edge.site, edge.name)


def assert_measured_throughout(local: Database, edge: Edge, since: datetime, until: datetime) -> None:
    with local.session() as s:
        for node_id in edge.nodes:
            during = s.scalar(select(func.count()).select_from(MeasurementRow).where(
                MeasurementRow.node_id == node_id, MeasurementRow.stored_at >= since,
                MeasurementRow.stored_at <= until))
            assert during >= NEW_PER_PHASE, f"{node_id} stopped measuring while the centre was down"

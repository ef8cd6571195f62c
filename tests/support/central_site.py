"""A central site for the tests: the real API (uvicorn on 127.0.0.1) over a database, with gateway keys."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
from sqlalchemy import func, select

from db.api_keys import create_api_key
from db.database import Database, open_database
from db.models import Role
from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer
from tests.support.process_harness import (
    Proc,
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
)
from uplink.contract import INGEST_PATH, IngestBatch

SINKS = ["webhook-central"]


@dataclass
class Centre:
    url: str
    database: Database
    north: str  # gateway key of site north
    south: str  # gateway key of site south
    viewer: str
    server: ApiServer

    def post(self, batch: IngestBatch | bytes, key: str, **headers: str) -> httpx.Response:
        body = batch if isinstance(batch, bytes) else batch.model_dump_json().encode()
        return httpx.post(f"{self.url}{INGEST_PATH}", content=body, timeout=30,
                          headers={"Authorization": f"Bearer {key}", "Content-Type": "application/json", **headers})

    def get(self, path: str, **params: object) -> httpx.Response:
        """GET an /api/v1 path with the viewer key."""
        return httpx.get(f"{self.url}/api/v1{path}", params=params, timeout=30,  # type: ignore[arg-type]
                         headers={"Authorization": f"Bearer {self.viewer}"})

    def count(self, model: type) -> int:
        with self.database.session() as session:
            return session.scalar(select(func.count()).select_from(model)) or 0


@contextmanager
def serve_centre(db_url: str, **settings: object) -> Iterator[Centre]:
    database = open_database(db_url)
    with database.write() as session:
        north = create_api_key(session, name="gw-north-1", role=Role.GATEWAY, site="north")[1]
        south = create_api_key(session, name="gw-south-1", role=Role.GATEWAY, site="south")[1]
        viewer = create_api_key(session, name="viewer", role=Role.VIEWER)[1]
    try:
        with ApiServer(ApiSettings(database_url=db_url, central_alert_sinks=SINKS, **settings)) as server:
            yield Centre(server.base_url, database, north, south, viewer, server)
    finally:
        database.dispose()




@dataclass
class Edge:
    """A real gateway process polling one mock node over a pty and replicating to a centre."""

    gateway: Proc
    database_path: Path


@contextmanager
def north_edge(centre: Centre, tmp_path: Path, *, gateway_id: str, node_id: str, seed: int,
               **uplink: object) -> Iterator[Edge]:
    """A gateway of site north (its gateway key) with one node polled every 0.3 s, replicating to
    ``centre`` with short waits; ``uplink`` adds to or overrides its ``[uplink]`` settings."""
    links = tmp_path / "links"
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_node(node_id, seed))
    mock = start_mock_nodes(scenario, links, tmp_path)
    database_path = tmp_path / "gateway.db"
    config = tmp_path / "gateway.toml"
    config.write_text(gateway_config(
        database_path, [gateway_node(node_id, links, interval_s=0.3)],
        uplink={"url": centre.url, "key": centre.north, "gateway_id": gateway_id, "site": "north",
                "idle_s": 0.2, "timeout_s": 10.0, "backoff_base_s": 0.2, "backoff_cap_s": 1.0, **uplink},
    ))
    gateway = None
    try:
        wait_for_links(links, [node_id], mock)
        gateway = start_gateway(config, tmp_path)
        yield Edge(gateway, database_path)
    finally:
        for proc in (gateway, mock):
            if proc is not None:
                proc.close()

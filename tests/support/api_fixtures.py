"""Shared fixtures of the API and dashboard tests: a realistic database filled by the real
gateway polling real mock nodes, and the real API served by uvicorn on 127.0.0.1.

The fleet runs once per test session (~20-40 s: two quiet nodes and one that grows a notch
once every node has calibrated its threshold, and is flagged ``damage``), then the gateway and
mock nodes are stopped. Each test module
works on its own copy of that database file, so a module that changes baselines or
acknowledges alerts does not change what another module sees.
"""
from __future__ import annotations

import os
import socket
import sqlite3
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import uvicorn
from prometheus_client import generate_latest

from db.api_keys import create_api_key
from db.database import Database, open_database
from db.models import NodeRow, NodeState, Role
from service.app import create_app
from service.database import DatabaseGate
from service.metrics import metrics_registry
from service.server import uvicorn_config
from service.settings import ApiSettings
from tests.support.process_harness import (
    PYTHON,
    Proc,
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    wait_for_links,
    wait_until,
)

MOCK_ON_DEMAND = Path(__file__).with_name("mock_on_demand.py")
QUIET_NODES = ("pipe-a", "pipe-b")
DAMAGED_NODE = "pipe-c"
DEFECT_AXIAL_MM = 200.0
DEFECT_ANGLE_DEG = 90.0
CALIBRATED_TIMEOUT_S = 90.0  # commissioning and threshold calibration of every node (~8 s idle)
FLEET_TIMEOUT_S = 60.0  # then the notch is flagged and every node has its monitor measurements
MIN_MONITORS_PER_NODE = 6

def fleet_scenario() -> str:
    text = "".join(scenario_node(n, 300 + i) for i, n in enumerate(QUIET_NODES))
    # The notch is in the pipe from the first acquisition after the fleet's notch file appears
    # (tests/support/mock_on_demand.py): after calibration however long the machine makes it.
    return text + scenario_node(DAMAGED_NODE, 399, defect=(DEFECT_AXIAL_MM, DEFECT_ANGLE_DEG, 0.0))


def node_settings(node_id: str, link_dir: Path, interval_s: float = 0.3) -> dict:
    return gateway_node(node_id, link_dir, interval_s=interval_s)


@dataclass
class RunningFleet:
    """Mock nodes and a gateway writing into ``db_path`` until :meth:`stop`."""

    run_dir: Path
    db_path: Path
    mock: Proc
    gateway: Proc
    procs: list[Proc] = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"sqlite:///{self.db_path}"

    @property
    def notch_file(self) -> Path:
        """While this file exists the damaged node's pipe has its notch."""
        return self.run_dir / "notch"

    def put_notch_in(self) -> None:
        self.notch_file.write_text("")

    def stop(self) -> None:
        try:
            assert self.gateway.terminate(timeout_s=10) == 0, self.gateway.stderr[-3000:]
        finally:
            self.gateway.close()
            self.mock.close()


def start_fleet(run_dir: Path, interval_s: float = 0.3, *, gateway_nice: int = 0, nodes_nice: int = 0) -> RunningFleet:
    """Start the mock nodes (on pseudo-terminals) and the gateway; returns once ports exist.

    ``gateway_nice`` / ``nodes_nice``: CPU niceness of the two processes (the benchmark runs the
    gateway as its systemd unit does, and the simulated nodes, whose work real nodes do on their
    own hardware, behind everything)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    scenario = run_dir / "scenario.toml"
    scenario.write_text(fleet_scenario())
    links = run_dir / "links"
    ids = [*QUIET_NODES, DAMAGED_NODE]
    mock = Proc([PYTHON, str(MOCK_ON_DEMAND), "--scenario", str(scenario), "--link-dir", str(links)], run_dir, "mock",
                env={"PIPESENTRY_TEST_DEFECTS_FILE": str(run_dir / "notch")}, nice=nodes_nice)
    wait_for_links(links, ids, mock)
    db_path = run_dir / "gateway.db"
    config = run_dir / "gateway.toml"
    config.write_text(gateway_config(db_path, [node_settings(n, links, interval_s) for n in ids]))
    return RunningFleet(run_dir, db_path, mock, start_gateway(config, run_dir, nice=gateway_nice))


def _node_states(url: str) -> dict[str, NodeState]:
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            return {n: row.state for n in (*QUIET_NODES, DAMAGED_NODE) if (row := session.get(NodeRow, n)) is not None}
    finally:
        database.dispose()


def _all_calibrated(url: str) -> bool:
    states = _node_states(url)
    return len(states) == len(QUIET_NODES) + 1 and all(s == NodeState.OK for s in states.values())


def _fleet_is_realistic(url: str) -> bool:
    """The damaged node is flagged and every node has a few monitor measurements."""
    from sqlalchemy import func, select

    from db.models import DetectionRow

    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            damaged = session.get(NodeRow, DAMAGED_NODE)
            if damaged is None or damaged.state != NodeState.DAMAGE:
                return False
            counts = dict(
                session.execute(select(DetectionRow.node_id, func.count()).group_by(DetectionRow.node_id)).all()
            )
            return all(counts.get(n, 0) >= MIN_MONITORS_PER_NODE for n in (*QUIET_NODES, DAMAGED_NODE))
    finally:
        database.dispose()


_built_fleet_db: dict[str, Path] = {}  # the session's one fleet database, once built
_build_lock = threading.Lock()


def fleet_database(base_dir: Path) -> Path:
    """The session's fleet database file (built on first use, then reused by every module)."""
    with _build_lock:
        if "path" not in _built_fleet_db:
            fleet = start_fleet(base_dir / "fleet")
            try:
                wait_until(lambda: _all_calibrated(fleet.url), CALIBRATED_TIMEOUT_S, 0.5,
                           what="every node commissioned and calibrated (state ok)")
                fleet.put_notch_in()
                wait_until(
                    lambda: _fleet_is_realistic(fleet.url),
                    FLEET_TIMEOUT_S,
                    0.5,
                    what=f"{DAMAGED_NODE} flagged damage and {MIN_MONITORS_PER_NODE} monitor measurements per node",
                )
            except AssertionError as error:
                raise AssertionError(f"{error}\ngateway log tail:\n{fleet.gateway.stderr[-3000:]}") from None
            finally:
                fleet.stop()
            _built_fleet_db["path"] = fleet.db_path
        return _built_fleet_db["path"]


def copy_database(source: Path, target: Path) -> Path:
    """A consistent copy of a SQLite database (the online backup API, WAL included)."""
    src = sqlite3.connect(source)
    dst = sqlite3.connect(target)
    try:
        src.backup(dst)
    finally:
        dst.close()
        src.close()
    return target


@dataclass(frozen=True)
class Keys:
    viewer: str
    operator: str
    admin: str
    gateway: str  # of site "test-site": the central site's ingest


def create_test_keys(url: str) -> Keys:
    database = open_database(url, upgrade=False)
    try:
        with database.write() as session:
            tokens = {role: create_api_key(session, name=f"test-{role.value}", role=role)[1]
                      for role in (Role.VIEWER, Role.OPERATOR, Role.ADMIN)}
            tokens[Role.GATEWAY] = create_api_key(session, name="test-gateway", role=Role.GATEWAY, site="test-site")[1]
    finally:
        database.dispose()
    return Keys(tokens[Role.VIEWER], tokens[Role.OPERATOR], tokens[Role.ADMIN], tokens[Role.GATEWAY])


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class ApiServer:
    """The real app served by uvicorn on an ephemeral 127.0.0.1 port, in a thread."""

    def __init__(self, settings: ApiSettings) -> None:
        self.settings = settings
        self.port = free_port()
        # The same uvicorn settings as `pipesentry api` (the connection guard and its limits).
        self.server = uvicorn.Server(uvicorn_config(create_app(settings), settings, port=self.port,
                                                    log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> ApiServer:
        self.thread.start()
        wait_until(lambda: self.server.started, 20, 0.05, what="uvicorn started")
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(15)


@dataclass(frozen=True)
class Api:
    """What an API test needs: the server's address, the database behind it, keys per role."""

    base_url: str
    db_url: str
    keys: Keys
    prefix: str = "/api/v1"

    def client(self, key: str | None = None) -> httpx.Client:
        headers = {} if key is None else {"Authorization": f"Bearer {key}"}
        return httpx.Client(base_url=self.base_url, headers=headers, timeout=30.0)


def serve_copy_of_fleet(tmp_dir: Path, base_dir: Path, **settings: object) -> Iterator[Api]:
    """Copy the fleet database into ``tmp_dir``, add keys, serve it; yields an :class:`Api`."""
    db_path = copy_database(fleet_database(base_dir), tmp_dir / "api.db")
    url = f"sqlite:///{db_path}"
    keys = create_test_keys(url)
    with ApiServer(ApiSettings(database_url=url, **settings)) as server:
        yield Api(server.base_url, url, keys)


@pytest.fixture(scope="session")
def fleet_db_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fleet_database(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    """The API over a private copy of the fleet database (one per test module)."""
    yield from serve_copy_of_fleet(tmp_path_factory.mktemp("api"), tmp_path_factory.getbasetemp())


def assert_problem(response: httpx.Response, status: int, slug: str) -> dict:
    """The response is an RFC 9457 problem of this status and type, with no traceback in it."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json"), response.headers
    body = response.json()
    assert body["type"] == f"urn:pipesentry:problem:{slug}", body
    assert body["status"] == status and body["title"]
    assert "Traceback" not in response.text and 'File "' not in response.text
    return body


def api_metrics_text(database: Database) -> str:
    """What the API's /metrics says about ``database``: its registry over its own handle on the file."""
    gate = DatabaseGate(database.engine.url.render_as_string(hide_password=False), busy_timeout_ms=1000)
    try:
        return generate_latest(metrics_registry(gate)).decode()
    finally:
        gate.dispose()


def in_ci() -> bool:
    return os.environ.get("CI") == "true"

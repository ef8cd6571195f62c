"""What the API does when things are wrong: missing or old database, pruned or corrupt data,
oversized requests, cross-site callers. Always a problem document, never a traceback."""
from __future__ import annotations

import sqlite3
from datetime import timedelta
from pathlib import Path

import httpx
import pytest

from db.database import open_database
from db.retention import prune_traces
from service.settings import ApiSettings
from tests.support.api_fixtures import (
    DAMAGED_NODE,
    QUIET_NODES,
    ApiServer,
    assert_problem,
    copy_database,
    create_test_keys,
    fleet_database,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]  # a gateway fleet and API servers


@pytest.fixture(scope="module")
def fleet_copy(tmp_path_factory: pytest.TempPathFactory):
    """A private copy of the fleet database, its URL and test keys."""
    path = copy_database(fleet_database(tmp_path_factory.getbasetemp()), tmp_path_factory.mktemp("fail") / "api.db")
    url = f"sqlite:///{path}"
    return path, url, create_test_keys(url)


def bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def test_missing_database_is_not_ready_and_is_never_created(tmp_path: Path):
    path = tmp_path / "absent.db"
    with ApiServer(ApiSettings(database_url=f"sqlite:///{path}")) as server:
        assert httpx.get(f"{server.base_url}/healthz").status_code == 200
        body = assert_problem(httpx.get(f"{server.base_url}/readyz"), 503, "storage-unavailable")
        assert "no database file" in body["detail"]
        assert str(tmp_path) not in body["detail"]  # answered without a key: the server's paths stay on it
        response = httpx.get(f"{server.base_url}/api/v1/nodes", headers=bearer("psk_anything"))
        assert_problem(response, 503, "storage-unavailable")
        assert response.headers["retry-after"]
    assert not path.exists()


def test_database_without_schema_is_not_ready_and_not_migrated(tmp_path: Path):
    path = tmp_path / "empty.db"
    sqlite3.connect(path).close()
    with ApiServer(ApiSettings(database_url=f"sqlite:///{path}")) as server:
        body = assert_problem(httpx.get(f"{server.base_url}/readyz"), 503, "schema-out-of-date")
        assert "migrate it by starting the gateway" in body["detail"]
        assert_problem(httpx.get(f"{server.base_url}/api/v1/nodes", headers=bearer("x")), 503, "schema-out-of-date")
    tables = sqlite3.connect(path).execute("SELECT name FROM sqlite_master WHERE type='table'").fetchall()
    assert tables == []


def test_database_at_an_unknown_revision_is_not_ready(fleet_copy, tmp_path: Path):
    path = copy_database(fleet_copy[0], tmp_path / "future.db")
    with sqlite3.connect(path) as connection:
        connection.execute("UPDATE alembic_version SET version_num = '9999_from_the_future'")
    with ApiServer(ApiSettings(database_url=f"sqlite:///{path}")) as server:
        body = assert_problem(httpx.get(f"{server.base_url}/readyz"), 503, "schema-out-of-date")
        assert "9999_from_the_future" in body["detail"]


def test_pruned_traces_are_a_410_problem_and_the_metadata_and_maps_stay(fleet_copy):
    _, url, keys = fleet_copy
    with ApiServer(ApiSettings(database_url=url)) as server, \
            httpx.Client(base_url=server.base_url, headers=bearer(keys.viewer)) as client:
        oldest = client.get(f"/api/v1/nodes/{QUIET_NODES[0]}/measurements",
                            params={"kind": "monitor", "order": "asc", "limit": 1}).json()["items"][0]
        database = open_database(url, upgrade=False)
        try:
            assert prune_traces(database.write, older_than=timedelta(seconds=0), batch_size=100) > 0
        finally:
            database.dispose()
        for suffix in ("traces", "traces.npz", "traces.csv"):
            body = assert_problem(client.get(f"/api/v1/measurements/{oldest['id']}/{suffix}"), 410, "traces-pruned")
            assert "pruned" in body["detail"]
        detail = client.get(f"/api/v1/measurements/{oldest['id']}").json()
        assert detail["traces_available"] is False and detail["traces_pruned_at"] is not None
        assert client.get(f"/api/v1/measurements/{oldest['id']}/di-maps/gateway").status_code == 200
        # A pruned measurement cannot become a baseline (it could not be re-imaged).
        with httpx.Client(base_url=server.base_url, headers=bearer(keys.operator)) as operator:
            refused = operator.post(f"/api/v1/nodes/{QUIET_NODES[0]}/baselines",
                                    json={"measurement_id": oldest["id"], "reason": "too late"})
        assert_problem(refused, 409, "baseline-refused")


def test_corrupt_stored_map_is_a_500_problem_without_internals(fleet_copy, tmp_path: Path):
    path = copy_database(fleet_copy[0], tmp_path / "corrupt.db")
    with sqlite3.connect(path) as connection:
        map_id, measurement_id = connection.execute(
            "SELECT id, measurement_id FROM di_maps WHERE source = 'gateway' ORDER BY id DESC LIMIT 1").fetchone()
        connection.execute("UPDATE di_maps SET pixels_blob = x'00010203' WHERE id = ?", (map_id,))
    with ApiServer(ApiSettings(database_url=f"sqlite:///{path}")) as server, \
            httpx.Client(base_url=server.base_url, headers=bearer(fleet_copy[2].viewer)) as client:
        for suffix in ("", ".png"):
            body = assert_problem(client.get(f"/api/v1/measurements/{measurement_id}/di-maps/gateway{suffix}"),
                                  500, "corrupt-data")
            assert "sha256" not in body.get("detail", "").lower()
        assert client.get(f"/api/v1/measurements/{measurement_id}/di-maps/node").status_code == 200


def test_oversized_body_is_413_whether_declared_or_streamed(fleet_copy):
    _, url, keys = fleet_copy
    limit = 1024
    with ApiServer(ApiSettings(database_url=url, max_body_bytes=limit)) as server, \
            httpx.Client(base_url=server.base_url, headers=bearer(keys.operator)) as client:
        target = f"/api/v1/nodes/{DAMAGED_NODE}/baselines"
        big = {"measurement_id": 1, "reason": "x" * (2 * limit)}
        assert_problem(client.post(target, json=big), 413, "payload-too-large")

        def chunks():  # no Content-Length: the limit is enforced on the bytes as they arrive
            yield b'{"measurement_id": 1, "reason": "'
            for _ in range(4):
                yield b"y" * limit
            yield b'"}'

        streamed = client.post(target, content=chunks(), headers={"Content-Type": "application/json"})
        assert_problem(streamed, 413, "payload-too-large")
        small = client.post(target, json={"measurement_id": 999999, "reason": "fits"})
        assert_problem(small, 404, "not-found")


def test_cors_is_off_by_default_and_answers_only_configured_origins(fleet_copy):
    _, url, keys = fleet_copy
    preflight = {"Origin": "https://ops.example", "Access-Control-Request-Method": "GET",
                 "Access-Control-Request-Headers": "authorization"}
    with ApiServer(ApiSettings(database_url=url)) as server:
        response = httpx.get(f"{server.base_url}/api/v1/nodes",
                             headers={"Origin": "https://ops.example", **bearer(keys.viewer)})
        assert "access-control-allow-origin" not in response.headers
        assert "access-control-allow-origin" not in httpx.options(f"{server.base_url}/api/v1/nodes",
                                                                   headers=preflight).headers
    with ApiServer(ApiSettings(database_url=url, cors_origins=["https://ops.example"])) as server:
        allowed = httpx.options(f"{server.base_url}/api/v1/nodes", headers=preflight)
        assert allowed.headers["access-control-allow-origin"] == "https://ops.example"
        for method in ("POST", "PATCH", "DELETE"):  # every method an operator's browser calls the API with
            cross_site = httpx.options(f"{server.base_url}/api/v1/nodes/{DAMAGED_NODE}",
                                       headers={**preflight, "Access-Control-Request-Method": method})
            assert cross_site.status_code == 200, (method, cross_site.text)
            assert method in cross_site.headers["access-control-allow-methods"]
        other = httpx.options(f"{server.base_url}/api/v1/nodes", headers={**preflight, "Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers


def test_metrics_can_be_opened_for_a_trusted_scrape_network(fleet_copy):
    _, url, _ = fleet_copy
    with ApiServer(ApiSettings(database_url=url)) as server:
        assert_problem(httpx.get(f"{server.base_url}/metrics"), 401, "unauthorized")
    with ApiServer(ApiSettings(database_url=url, metrics_require_key=False)) as server:
        response = httpx.get(f"{server.base_url}/metrics")
        assert response.status_code == 200 and "pipesentry_node_up" in response.text


def test_metrics_report_the_database_down_instead_of_failing(tmp_path: Path):
    with ApiServer(ApiSettings(database_url=f"sqlite:///{tmp_path / 'absent.db'}",
                               metrics_require_key=False)) as server:
        response = httpx.get(f"{server.base_url}/metrics")
    assert response.status_code == 200 and "pipesentry_database_up 0.0" in response.text

"""HEAD is GET without the body on every route (RFC 9110 9.3.2): uptime checkers and load balancers
probe with it. The real app under uvicorn on 127.0.0.1, over a real SQLite file."""
from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from db.database import open_database
from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer, create_test_keys

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def served(tmp_path: Path):
    url = f"sqlite:///{tmp_path / 'api.db'}"
    open_database(url).dispose()  # created at this release's schema
    keys = create_test_keys(url)
    with ApiServer(ApiSettings(database_url=url)) as server:
        yield server, keys


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/api/v1/nodes", "/metrics", "/static/dashboard.js", "/"])
def test_head_answers_what_get_answers_without_the_body(served, path):
    server, keys = served
    auth = {"Authorization": f"Bearer {keys.viewer}"}
    get = httpx.get(f"{server.base_url}{path}", headers=auth, timeout=10)
    head = httpx.head(f"{server.base_url}{path}", headers=auth, timeout=10)
    assert get.status_code == 200 and head.status_code == 200
    assert head.content == b""
    assert head.headers["content-type"] == get.headers["content-type"]
    if "content-length" in get.headers:
        assert head.headers["content-length"] == get.headers["content-length"]


def test_head_needs_the_same_key_as_get_and_a_route_without_get_still_refuses_it(served):
    server, _ = served
    anonymous = httpx.head(f"{server.base_url}/api/v1/nodes", timeout=10)
    assert anonymous.status_code == 401 and anonymous.content == b""
    assert anonymous.headers["www-authenticate"] == "Bearer"
    post_only = httpx.head(f"{server.base_url}/api/v1/ingest/batches", timeout=10)
    assert post_only.status_code == 405 and post_only.headers["allow"] == "POST"

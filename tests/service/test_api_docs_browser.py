"""Swagger UI at /api/v1/docs renders in headless Chromium with no internet: its assets come from the
installed package, not a CDN (issue 16, item 7: the page was blank on an edge computer offline)."""
from __future__ import annotations

import httpx
import pytest

from service.routes.api_docs import ASSETS_PATH
from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.timeout(120)]

WAIT_MS = 30_000


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # The docs need no data: an API before the gateway has created its database serves them too.
    url = f"sqlite:///{tmp_path_factory.mktemp('docs') / 'not-yet.db'}"
    with ApiServer(ApiSettings(database_url=url)) as running:
        yield running


def test_swagger_ui_renders_every_operation_offline(server, page):
    page.goto(f"{server.base_url}/api/v1/docs")
    title = page.locator(".swagger-ui .info .title")
    title.wait_for(timeout=WAIT_MS)
    assert "PipeSentry operator API" in title.inner_text()
    page.locator(".opblock").first.wait_for(timeout=WAIT_MS)
    schema = httpx.get(f"{server.base_url}/api/v1/openapi.json", timeout=10).json()
    operations = sum(len(methods) for methods in schema["paths"].values())
    assert page.locator(".opblock").count() == operations
    assert page.seen.outside_requests == []  # the fixture also asserts it at teardown


def test_the_page_names_only_local_assets(server):
    html = httpx.get(f"{server.base_url}/api/v1/docs", timeout=10).text
    assert f'src="{ASSETS_PATH}/swagger-ui-bundle.js"' in html and f'href="{ASSETS_PATH}/swagger-ui.css"' in html
    assert "cdn." not in html and "unpkg" not in html
    asset = httpx.get(f"{server.base_url}{ASSETS_PATH}/swagger-ui-bundle.js", timeout=10)
    assert asset.status_code == 200 and len(asset.content) > 500_000
    assert "no-store" not in asset.headers.get("cache-control", "")

"""Every route the server answers has a role decision, the ones outside the OpenAPI document included.

tests/service/test_api_auth.py walks the documented operations over HTTP with every key state
(tests/support/role_matrix.py is its table). Here the routes are enumerated from the application
itself, so a route hidden from the schema (``include_in_schema=False``) or a new mount cannot
slip past: each must be in the table or named below as public, and a public one must hold no
fleet data.
"""
from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi import FastAPI
from starlette.routing import Mount, Route

from service.app import create_app
from service.settings import ApiSettings
from tests.support.api_fixtures import DAMAGED_NODE, QUIET_NODES, Api
from tests.support.role_matrix import REQUIRED_ROLE

pytestmark = pytest.mark.timeout(120)

# Served without a key and outside the OpenAPI document: what each is, and a path to fetch.
PUBLIC_UNDOCUMENTED = {
    ("get", "/"): "/",  # the dashboard's static shell
    ("get", "/api/v1/openapi.json"): "/api/v1/openapi.json",
    ("get", "/api/v1/docs"): "/api/v1/docs",  # Swagger UI
    ("get", "/static/*"): "/static/dashboard.js",
    ("get", "/swagger-ui/*"): "/swagger-ui/swagger-ui-bundle.js",
}


def served_routes(app: FastAPI) -> Iterator[tuple[str, str]]:
    """(method, path) of every route and mount the app answers (HEAD left out: it follows GET)."""
    for route in app.routes:
        included = getattr(route, "original_router", None)  # FastAPI's included routers
        if included is not None:
            prefix = route.include_context.prefix  # type: ignore[attr-defined]
            for sub in included.routes:
                for method in sorted(getattr(sub, "methods", None) or ()):
                    if method != "HEAD":
                        yield method.lower(), prefix + sub.path
        elif isinstance(route, Mount):
            yield "get", route.path + "/*"
        elif isinstance(route, Route):
            for method in sorted(route.methods or ()):
                if method != "HEAD":
                    yield method.lower(), route.path
        else:
            raise AssertionError(f"a route of a kind this test cannot enumerate: {route!r}")


def test_every_route_the_app_serves_has_a_role_decision(tmp_path):
    app = create_app(ApiSettings(database_url=f"sqlite:///{tmp_path / 'absent.db'}"))
    served = set(served_routes(app))
    print(f"role matrix: {len(served)} routes served, {len(REQUIRED_ROLE)} documented operations with a role, "
          f"{len(PUBLIC_UNDOCUMENTED)} public routes outside the schema")
    assert served - set(REQUIRED_ROLE) - set(PUBLIC_UNDOCUMENTED) == set(), "routes without a role decision"
    assert (set(REQUIRED_ROLE) | set(PUBLIC_UNDOCUMENTED)) - served == set(), "decisions about routes that are gone"


@pytest.mark.parametrize("route", sorted(PUBLIC_UNDOCUMENTED))
def test_a_public_route_outside_the_schema_holds_no_fleet_data(api: Api, route):
    with api.client() as anonymous:
        response = anonymous.get(PUBLIC_UNDOCUMENTED[route])
    assert response.status_code == 200
    assert not any(node in response.text for node in (*QUIET_NODES, DAMAGED_NODE))
    assert "psk_" not in response.text

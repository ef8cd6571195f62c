"""Role boundaries: nothing is read or changed without a key, and each role gets exactly its share.

viewer reads; operator also changes baselines and handles alerts; admin also manages keys and nodes;
a gateway key (scoped to its site) only ingests its gateway's batches at a central site.
Only /healthz, /readyz and the dashboard's static shell answer without a key.
"""
from __future__ import annotations

import uuid

import pytest

from db.models import Role
from service.deps import Caller, VerifiedKeys
from tests.support.api_fixtures import DAMAGED_NODE, Api, assert_problem
from tests.support.role_matrix import REQUIRED_ROLE, WEAKER

pytestmark = pytest.mark.timeout(240)

# Bodies valid enough to pass validation, pointing at nothing that exists: a permitted
# call answers 404 or 201, never changes the shared fleet in a way other tests notice.
BODIES = {
    ("post", "/api/v1/nodes/{node_id}/baselines"): {"measurement_id": 999999, "reason": "auth test"},
    ("post", "/api/v1/nodes/{node_id}/baselines/{baseline_id}/activate"): {"reason": "auth test"},
    ("post", "/api/v1/keys"): {"name": "auth-test", "role": "viewer"},
    ("patch", "/api/v1/nodes/{node_id}"): {"notes": "auth test"},
    ("post", "/api/v1/nodes/{node_id}/decommission"): {"reason": "auth test"},
}
# Operations whose permitted call would take a fleet node out of service: aimed at no node (404).
NO_SUCH_NODE = {("post", "/api/v1/nodes/{node_id}/decommission"), ("post", "/api/v1/nodes/{node_id}/recommission")}


def concrete(path: str) -> str:
    return (path.replace("{node_id}", DAMAGED_NODE).replace("{measurement_id}", "1")
            .replace("{baseline_id}", "999999").replace("{source}", "gateway")
            .replace("{alert_id}", str(uuid.uuid4())).replace("{key_id}", "999999"))


def call(client, method: str, path: str):
    url = concrete(path)
    if (method, path) in NO_SUCH_NODE:
        url = url.replace(DAMAGED_NODE, "no-such-node")
    return client.request(method.upper(), url, json=BODIES.get((method, path)))


def test_every_documented_operation_has_a_stated_role(api: Api):
    with api.client(api.keys.viewer) as client:
        schema = client.get("/api/v1/openapi.json").json()
    documented = {(m, p) for p, item in schema["paths"].items() for m in item}
    assert documented == set(REQUIRED_ROLE)


@pytest.mark.parametrize(("method", "path"), [k for k, role in REQUIRED_ROLE.items() if role])
def test_no_key_is_401_with_a_bearer_challenge(api: Api, method, path):
    with api.client() as anonymous:
        response = call(anonymous, method, path)
    assert_problem(response, 401, "unauthorized")
    assert response.headers["www-authenticate"] == "Bearer"


@pytest.mark.parametrize(("method", "path"), [k for k, role in REQUIRED_ROLE.items() if role])
def test_unknown_key_is_401(api: Api, method, path):
    with api.client("psk_" + "x" * 43) as stranger:
        assert_problem(call(stranger, method, path), 401, "unauthorized")


@pytest.mark.parametrize(
    ("method", "path", "weaker"),
    [(m, p, w) for (m, p), role in REQUIRED_ROLE.items() if role for w in WEAKER[role]],
)
def test_weaker_role_is_403(api: Api, method, path, weaker):
    with api.client(getattr(api.keys, weaker)) as client:
        body = assert_problem(call(client, method, path), 403, "forbidden")
    # A gateway key is stopped at the first gate it meets (a router's viewer gate, before an admin one).
    assert REQUIRED_ROLE[(method, path)] in body["detail"] or "this key is gateway" in body["detail"]


@pytest.mark.parametrize(("method", "path"), [k for k, role in REQUIRED_ROLE.items() if role])
def test_sufficient_role_passes_the_gate(api: Api, method, path):
    role = REQUIRED_ROLE[(method, path)]
    with api.client(getattr(api.keys, role)) as client:
        response = call(client, method, path)
    assert response.status_code not in (401, 403), response.text
    assert response.status_code < 500, response.text


def test_key_in_x_api_key_header_is_accepted(api: Api):
    with api.client() as client:
        assert client.get("/api/v1/nodes", headers={"X-API-Key": api.keys.viewer}).status_code == 200
        assert_problem(client.get("/api/v1/nodes", headers={"Authorization": f"Basic {api.keys.viewer}"}),
                       401, "unauthorized")


def test_absurdly_long_key_is_refused_without_a_lookup(api: Api):
    with api.client("k" * 100_000) as client:
        response = client.get("/api/v1/nodes")
    assert response.status_code in (401, 431)


def test_dashboard_shell_needs_no_key_but_holds_no_data(api: Api):
    with api.client() as anonymous:
        page = anonymous.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert DAMAGED_NODE not in page.text
        assert "default-src 'self'" in page.headers["content-security-policy"]
        assert anonymous.get("/static/dashboard.js").status_code == 200


def test_verified_keys_expire_after_their_ttl_and_can_be_forgotten():
    clock = [100.0]
    keys = VerifiedKeys(ttl_s=10.0, clock=lambda: clock[0])
    alice = Caller(key_id=1, name="alice", role=Role.OPERATOR)
    keys.put("h1", alice)
    clock[0] += 9.0
    assert keys.get("h1") == alice
    clock[0] += 2.0
    assert keys.get("h1") is None  # past the TTL: looked up again
    keys.put("h1", alice)
    keys.forget(1)
    assert keys.get("h1") is None  # revoked through this process: at once

"""Hostile input gets a clear 4xx problem, never a 500, and changes nothing.

Out-of-range instants and ids, forged cursors, oversized and deeply nested bodies, path
traversal, SQL metacharacters and bytes that are not UTF-8, sent to the real server over the
fleet database. Every answer must be a problem document without a traceback or a decoder's
message, and the fleet must read the same afterwards.
"""
from __future__ import annotations

import base64
import json
import socket
from urllib.parse import quote

import pytest

from tests.support.api_fixtures import DAMAGED_NODE, QUIET_NODES, Api, assert_problem

pytestmark = pytest.mark.timeout(180)

NODE = f"/api/v1/nodes/{DAMAGED_NODE}"
LISTS = [f"{NODE}/measurements", f"{NODE}/detections", "/api/v1/detections"]
OUT_OF_RANGE_INSTANTS = ["9999-12-31T23:59:59-14:00", "0001-01-01T00:00:00+14:00"]
# Words of Python's decoders and drivers: none may reach a client.
LEAKS = ("codec", "padding", "Expecting", "line 1 column", "int too large", "Overflow", "sqlite", "Traceback")


def cursor(payload: object) -> str:
    return base64.urlsafe_b64encode(json.dumps(payload).encode()).decode().rstrip("=")


FORGED_CURSORS = {
    "id beyond int64": cursor({"v": 1, "t": "2026-01-01T00:00:00+00:00", "id": 2**64}),
    "id below int64": cursor({"v": 1, "t": "2026-01-01T00:00:00+00:00", "id": -(2**63) - 1}),
    "instant out of range": cursor({"v": 1, "t": "9999-12-31T23:59:59-14:00", "id": 1}),
    "instant without offset": cursor({"v": 1, "t": "2026-01-01T00:00:00", "id": 1}),
    "id not a number": cursor({"v": 1, "t": "2026-01-01T00:00:00+00:00", "id": "1 OR 1=1"}),
    "not an object": cursor([1, 2, 3]),
    "nested": cursor({"v": 1, "t": {"t": {"t": "x"}}, "id": 1}),
    "not base64": "!!!!",
    "bad padding": "abc",
    "not ascii": "é" * 8,
    "base64 of bytes that are not UTF-8": base64.urlsafe_b64encode(b"\xff\xfe\xfd").decode(),
}
ALERT_CURSORS = {
    "instant out of range": cursor({"t": "9999-12-31T23:59:59-14:00", "id": "00000000-0000-0000-0000-000000000000"}),
    "not ascii": "é" * 8,
    "not base64": "!!!!",
}


def no_leak(body: dict) -> None:
    text = json.dumps(body)
    assert not any(word in text for word in LEAKS), text


@pytest.mark.parametrize("instant", OUT_OF_RANGE_INSTANTS)
@pytest.mark.parametrize("path", LISTS)
@pytest.mark.parametrize("name", ["start", "end"])
def test_an_instant_beyond_the_calendar_in_utc_is_a_422(api: Api, path, name, instant):
    with api.client(api.keys.viewer) as client:
        body = assert_problem(client.get(path, params={name: instant}), 422, "validation-error")
    assert body["errors"][0]["loc"] == ["query", name]
    no_leak(body)


@pytest.mark.parametrize("forged", sorted(FORGED_CURSORS))
@pytest.mark.parametrize("path", LISTS)
def test_a_forged_cursor_is_a_400_that_names_no_decoder(api: Api, path, forged):
    with api.client(api.keys.viewer) as client:
        body = assert_problem(client.get(path, params={"cursor": FORGED_CURSORS[forged]}), 400, "invalid-cursor")
    no_leak(body)


@pytest.mark.parametrize("forged", sorted(ALERT_CURSORS))
def test_a_forged_alert_cursor_is_a_400_that_names_no_decoder(api: Api, forged):
    with api.client(api.keys.viewer) as client:
        body = assert_problem(client.get("/api/v1/alerts", params={"cursor": ALERT_CURSORS[forged]}), 400,
                              "invalid-cursor")
    no_leak(body)


@pytest.mark.parametrize("path", [
    "/api/v1/measurements/9223372036854775808", "/api/v1/measurements/0", "/api/v1/measurements/-1",
    "/api/v1/measurements/1e3", f"{NODE}/baselines/99999999999999999999/activate",
    "/api/v1/keys/18446744073709551616", f"{NODE}/measurements?limit=0", f"{NODE}/measurements?limit=1001",
    f"{NODE}/measurements?limit=99999999999999999999", f"{NODE}/measurements?order=sideways",
    "/api/v1/alerts/not-a-uuid", f"/api/v1/nodes/{'n' * 65}",
])
def test_an_id_or_number_out_of_range_is_a_422(api: Api, path):
    method = "POST" if path.endswith("/activate") else "DELETE" if "/keys/" in path else "GET"
    with api.client(api.keys.admin) as client:
        response = client.request(method, path, json={"reason": "x"} if method == "POST" else None)
    body = assert_problem(response, 422, "validation-error")
    no_leak(body)


def test_a_body_over_the_limit_is_a_413_and_a_deeply_nested_one_a_4xx(api: Api):
    with api.client(api.keys.operator) as client:
        assert_problem(client.post(f"{NODE}/baselines", content=b"[" * 70_000,
                                   headers={"Content-Type": "application/json"}), 413, "payload-too-large")
        nested = '{"measurement_id": 1, "reason": ' + "[" * 30_000 + "]" * 30_000 + "}"  # within the body limit
        response = client.post(f"{NODE}/baselines", content=nested, headers={"Content-Type": "application/json"})
    assert 400 <= response.status_code < 500, response.text
    no_leak(response.json())


@pytest.mark.parametrize("body", [b'{"reason": "\xff\xfe bad"}', "{\"reason\": \"é\"}".encode("latin-1")])
def test_a_body_that_is_not_utf8_is_the_documented_400(api: Api, body):
    with api.client(api.keys.admin) as client:
        response = client.post(f"{NODE}/decommission", content=body, headers={"Content-Type": "application/json"})
    problem = assert_problem(response, 400, "bad-request")
    assert problem["detail"] == "the request body is not JSON in UTF-8"
    with api.client(api.keys.viewer) as client:
        assert client.get(NODE).json()["decommissioned"] is None  # nothing changed


@pytest.mark.parametrize("path", [
    "/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/%2e%2e/etc/passwd", "/static/..%2f..%2fpyproject.toml",
    "/swagger-ui/%2e%2e/%2e%2e/%2e%2e/etc/passwd", "/static/%00", "/static//etc/passwd",
])
def test_a_traversal_reaches_no_file_outside_the_static_folders(api: Api, path):
    with socket.create_connection(("127.0.0.1", int(api.base_url.rsplit(":", 1)[1])), timeout=10) as sock:
        # Raw, so that no client normalises the dots away before they reach the server.
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n".encode())
        answer = b""
        for _ in range(1000):  # bounded: the server closes after its answer
            chunk = sock.recv(65536)
            if not chunk:
                break
            answer += chunk
    status = int(answer.split(b" ", 2)[1])
    assert status in (400, 404), answer[:300]
    assert b"root:" not in answer and b"[project]" not in answer


@pytest.mark.parametrize("node_id", ["x' OR '1'='1", "pipe-a'; DROP TABLE nodes;--", 'pipe-a" --', "%",
                                     "pipe-%", "\\", "pipe-a\u0000"])
def test_sql_metacharacters_are_data_not_code(api: Api, node_id):
    with api.client(api.keys.viewer) as client:
        response = client.get(f"/api/v1/nodes/{quote(node_id, safe='')}")
        assert response.status_code == 422, response.text
        no_leak(response.json())
        for listing in ("/api/v1/detections", "/api/v1/alerts"):
            listed = client.get(listing, params={"node_id": node_id})
            assert listed.status_code == 422, listed.text  # not a node id the gateway accepts
        fleet = {n["node_id"] for n in client.get("/api/v1/nodes").json()}
    assert fleet >= {*QUIET_NODES, DAMAGED_NODE}


def test_a_key_name_with_sql_and_control_characters_round_trips_as_text(api: Api):
    name = "o'brien\"; DROP TABLE api_keys;--\n\x1b[31mred"
    with api.client(api.keys.admin) as client:
        created = client.post("/api/v1/keys", json={"name": name, "role": "viewer"})
        if created.status_code == 422:  # refusing control characters outright is as good
            return
        assert created.status_code == 201, created.text
        assert [k["name"] for k in client.get("/api/v1/keys").json() if k["id"] == created.json()["id"]] == [name]


def test_a_405_names_every_method_the_path_allows(api: Api):
    with api.client(api.keys.admin) as client:
        response = client.delete(NODE)
    assert_problem(response, 405, "method-not-allowed")
    assert set(response.headers["allow"].replace(" ", "").split(",")) == {"GET", "PATCH"}

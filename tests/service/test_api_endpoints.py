"""The operator API over HTTP (uvicorn on 127.0.0.1) on a database filled by the real gateway.

The fleet: two quiet nodes and one (``pipe-c``) that grew a notch and was flagged damage.
"""
from __future__ import annotations

import io
import uuid

import numpy as np
import pytest

from db.database import open_database
from db.measurements import get_measurement, load_traces_volts
from imaging.formats import load_csv, load_npz
from tests.support.api_fixtures import DAMAGED_NODE, QUIET_NODES, Api, assert_problem

pytestmark = pytest.mark.timeout(240)
ALL_NODES = sorted([*QUIET_NODES, DAMAGED_NODE])


@pytest.fixture(scope="module")
def viewer(api: Api):
    with api.client(api.keys.viewer) as client:
        yield client


@pytest.fixture(scope="module")
def operator(api: Api):
    with api.client(api.keys.operator) as client:
        yield client


@pytest.fixture(scope="module")
def admin(api: Api):
    with api.client(api.keys.admin) as client:
        yield client


def latest_monitor_id(viewer, node_id: str) -> int:
    return viewer.get(f"/api/v1/nodes/{node_id}/detections/latest").json()["measurement_id"]


# ------------------------------------------------------------------ nodes

def test_node_health_shows_who_answers_on_the_port_its_boot_and_the_settings_it_applied(api: Api, viewer):
    from db.nodes import record_node_link

    for node in viewer.get("/api/v1/nodes").json():  # as the real gateway left them
        health = node["health"]
        assert health["reported_node_id"] == node["node_id"] and health["problems"] == []
        assert health["boot_id"] > 0 and health["reboots"] == 0
        assert health["applied_settings"] == {"excitation_hz": 85000.0, "cycles": 5, "averaging": 10,
                                              "channel_mask": 0xFFFF, "n_samples": 6000}
    problem = "node_id: the node on /dev/ttyUSB3 reports 'pipe-x', configured 'pipe-a'"
    database = open_database(api.db_url, upgrade=False)
    try:
        with database.write() as session:
            record_node_link(session, DAMAGED_NODE, reported_node_id="pipe-x", boot_id=77, applied_settings=None,
                             problems=[problem], rebooted=True)
        health = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}").json()["health"]
        assert (health["reported_node_id"], health["boot_id"], health["reboots"]) == ("pipe-x", 77, 1)
        assert health["problems"] == [problem] and health["applied_settings"] is None and health["last_reboot_at"]
    finally:
        database.dispose()


def test_node_list_shows_identity_health_state_and_baseline_of_every_node(viewer):
    nodes = viewer.get("/api/v1/nodes").json()
    assert [n["node_id"] for n in nodes] == ALL_NODES
    for node in nodes:
        assert node["n_channels"] == 16 and node["port_url"].endswith(node["node_id"])
        assert node["health"]["last_seen_at"].endswith("Z") or "+" in node["health"]["last_seen_at"]
        assert node["error_counters"]["node_crc_errors"] == 0
        assert node["active_baseline"]["created_by"] == "gateway"
        assert node["latest_di_peak"] > 0 and node["latest_threshold"] > 0
        assert node["latest_detection"]["peak_di"] == node["latest_di_peak"]
    by_id = {n["node_id"]: n for n in nodes}
    assert by_id[DAMAGED_NODE]["state"] == "damage"
    assert by_id[DAMAGED_NODE]["latest_di_peak"] > by_id[DAMAGED_NODE]["latest_threshold"]
    assert all(by_id[n]["state"] != "damage" for n in QUIET_NODES)


def test_node_detail_matches_its_entry_in_the_list(viewer):
    listed = {n["node_id"]: n for n in viewer.get("/api/v1/nodes").json()}
    for node_id in ALL_NODES:
        assert viewer.get(f"/api/v1/nodes/{node_id}").json() == listed[node_id]


def test_unknown_node_is_a_404_problem(viewer):
    assert_problem(viewer.get("/api/v1/nodes/no-such-node"), 404, "not-found")
    assert_problem(viewer.get("/api/v1/nodes/no-such-node/measurements"), 404, "not-found")


# ------------------------------------------------------------------ measurements and pagination

def test_measurement_pages_cover_every_measurement_once_newest_first(viewer):
    everything = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}/measurements", params={"limit": 1000}).json()
    assert everything["next_cursor"] is None
    seen, cursor = [], None
    for _ in range(100):
        page = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}/measurements",
                          params={"limit": 3, **({"cursor": cursor} if cursor else {})}).json()
        assert len(page["items"]) <= 3
        seen += page["items"]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == everything["items"]
    times = [m["acquired_at"] for m in seen]
    assert times == sorted(times, reverse=True)
    assert seen[-1]["kind"] == "baseline" and all(m["node_id"] == DAMAGED_NODE for m in seen)


def test_measurements_filter_by_time_range_and_kind_and_order(viewer):
    url = f"/api/v1/nodes/{DAMAGED_NODE}/measurements"
    items = viewer.get(url, params={"limit": 1000, "order": "asc"}).json()["items"]
    assert [m["acquired_at"] for m in items] == sorted(m["acquired_at"] for m in items)
    start, end = items[2]["acquired_at"], items[5]["acquired_at"]
    window = viewer.get(url, params={"start": start, "end": end, "order": "asc"}).json()["items"]
    assert [m["id"] for m in window] == [m["id"] for m in items[2:5]]  # [start, end)
    baselines = viewer.get(url, params={"kind": "baseline"}).json()["items"]
    assert baselines and {m["kind"] for m in baselines} == {"baseline"}


def test_bad_cursor_is_400_and_naive_time_is_422(viewer):
    url = f"/api/v1/nodes/{DAMAGED_NODE}/measurements"
    assert_problem(viewer.get(url, params={"cursor": "not-a-cursor"}), 400, "invalid-cursor")
    body = assert_problem(viewer.get(url, params={"start": "2026-01-01T00:00:00"}), 422, "validation-error")
    assert body["errors"][0]["loc"] == ["query", "start"]
    assert_problem(viewer.get(url, params={"limit": 0}), 422, "validation-error")


def test_measurement_detail_lists_both_maps_and_the_verdict(viewer):
    measurement_id = latest_monitor_id(viewer, DAMAGED_NODE)
    detail = viewer.get(f"/api/v1/measurements/{measurement_id}").json()
    assert detail["kind"] == "monitor" and detail["traces_available"] is True
    assert {m["source"] for m in detail["di_maps"]} == {"node", "gateway"}
    assert detail["detection"]["state"] == "damage"
    assert viewer.get(f"/api/v1/measurements/{measurement_id}/di-maps").json() == detail["di_maps"]
    assert_problem(viewer.get("/api/v1/measurements/999999"), 404, "not-found")


# ------------------------------------------------------------------ raw traces

def test_traces_as_npz_csv_and_json_equal_the_stored_codes_times_volts_per_code(api: Api, viewer):
    measurement_id = latest_monitor_id(viewer, DAMAGED_NODE)
    database = open_database(api.db_url, upgrade=False)
    try:
        with database.session() as session:
            expected = load_traces_volts(get_measurement(session, measurement_id))
    finally:
        database.dispose()
    npz = viewer.get(f"/api/v1/measurements/{measurement_id}/traces.npz")
    assert npz.headers["content-type"] == "application/octet-stream"
    from_npz = _load_bytes(npz.content, ".npz", load_npz)
    np.testing.assert_array_equal(from_npz.traces, expected)
    assert from_npz.rx_angles_deg.shape == (16,) and from_npz.tx_rx_distance_mm > 0
    csv = viewer.get(f"/api/v1/measurements/{measurement_id}/traces.csv")
    assert csv.headers["content-type"].startswith("text/csv")
    from_csv = _load_bytes(csv.content, ".csv", load_csv)
    np.testing.assert_allclose(from_csv.traces, expected, rtol=1e-6)
    assert from_csv.fs_hz == pytest.approx(from_npz.fs_hz)
    as_json = viewer.get(f"/api/v1/measurements/{measurement_id}/traces").json()
    np.testing.assert_array_equal(np.asarray(as_json["traces"], dtype=np.float32), expected)
    codes = viewer.get(f"/api/v1/measurements/{measurement_id}/traces", params={"units": "codes"}).json()
    np.testing.assert_allclose(np.asarray(codes["traces"]) * codes["volts_per_code"], expected, rtol=1e-6)


def test_exported_files_reproduce_the_map_the_gateway_made(viewer):
    """The .npz of a flagged record and of the baseline it was imaged against, analysed as an
    engineer would (imaging.analysis.analyze, the file's velocity and wall), give the peak the
    gateway stored."""
    from imaging.analysis import analyze

    measurement_id = latest_monitor_id(viewer, DAMAGED_NODE)
    detection = viewer.get(f"/api/v1/measurements/{measurement_id}").json()["detection"]
    current, baseline = (
        _load_bytes(viewer.get(f"/api/v1/measurements/{m}/traces.npz").content, ".npz", load_npz)
        for m in (measurement_id, detection["baseline_measurement_id"])
    )
    assert current.wall_mm == baseline.wall_mm == 4.0  # the fleet's gateway config (tests/support/process_harness)
    result = analyze(baseline, current, threshold=detection["threshold"], wall_mm=current.wall_mm)
    assert result.peak_di == pytest.approx(detection["peak_di"], rel=1e-6)
    assert (result.peak.axial_mm, result.peak.angle_deg) == pytest.approx(
        (detection["axial_mm"], detection["angle_deg"]), abs=1e-3)  # mm, degrees: the sub-pixel refinement
    unwalled = analyze(baseline, current, threshold=detection["threshold"], wall_mm=None)  # what files gave before
    assert unwalled.peak_di != pytest.approx(detection["peak_di"], rel=1e-3)  # measured: 2 % off, 2 mm off


def _load_bytes(content: bytes, suffix: str, loader):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"m{suffix}"
        path.write_bytes(content)
        return loader(path)


# ------------------------------------------------------------------ DI maps

@pytest.mark.parametrize("source", ["gateway", "node"])
def test_di_map_json_has_grid_pixels_and_estimate(viewer, source):
    measurement_id = latest_monitor_id(viewer, DAMAGED_NODE)
    di_map = viewer.get(f"/api/v1/measurements/{measurement_id}/di-maps/{source}").json()
    grid = di_map["grid"]
    assert di_map["source"] == source and di_map["measurement_id"] == measurement_id
    assert len(di_map["pixels"]) == grid["axial_count"] and len(di_map["pixels"][0]) == grid["angle_count"]
    assert max(max(v for v in row if v is not None) for row in di_map["pixels"]) == pytest.approx(di_map["peak_di"])
    estimate = di_map["estimate"]
    assert grid["axial_start_mm"] - grid["axial_step_mm"] <= estimate["axial_mm"]
    assert 0 <= estimate["angle_deg"] < 360


def test_gateway_map_estimate_is_the_detection_estimate(viewer):
    detection = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}/detections/latest").json()
    di_map = viewer.get(f"/api/v1/measurements/{detection['measurement_id']}/di-maps/gateway").json()
    assert di_map["estimate"]["axial_mm"] == pytest.approx(detection["axial_mm"])
    assert di_map["estimate"]["angle_deg"] == pytest.approx(detection["angle_deg"])


@pytest.mark.parametrize("source", ["gateway", "node"])
def test_di_map_png_is_an_image(viewer, source):
    measurement_id = latest_monitor_id(viewer, DAMAGED_NODE)
    response = viewer.get(f"/api/v1/measurements/{measurement_id}/di-maps/{source}.png")
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"
    assert response.content[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    image = matplotlib.image.imread(io.BytesIO(response.content), format="png")
    assert image.shape[0] > 200 and image.shape[1] > 300


def test_baseline_measurement_has_no_map_and_says_so(viewer):
    baseline_id = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}").json()["active_baseline"]["measurement_id"]
    assert_problem(viewer.get(f"/api/v1/measurements/{baseline_id}/di-maps/gateway"), 404, "not-found")
    assert_problem(viewer.get(f"/api/v1/measurements/{baseline_id}/di-maps/gateway.png"), 404, "not-found")
    assert_problem(viewer.get(f"/api/v1/measurements/{baseline_id}/di-maps/sideways"), 422, "validation-error")


# ------------------------------------------------------------------ detections

def test_detections_latest_first_per_node_and_fleet_wide(viewer):
    fleet = viewer.get("/api/v1/detections", params={"limit": 1000}).json()["items"]
    assert {d["node_id"] for d in fleet} == set(ALL_NODES)
    assert [d["created_at"] for d in fleet] == sorted((d["created_at"] for d in fleet), reverse=True)
    mine = viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}/detections", params={"limit": 1000}).json()["items"]
    assert mine == [d for d in fleet if d["node_id"] == DAMAGED_NODE]
    assert viewer.get(f"/api/v1/nodes/{DAMAGED_NODE}/detections/latest").json() == mine[0]
    damaged = viewer.get("/api/v1/detections", params={"state": "damage"}).json()["items"]
    assert damaged and all(d["state"] == "damage" and d["node_id"] == DAMAGED_NODE for d in damaged)
    flagged = damaged[0]
    assert flagged["peak_di"] > flagged["threshold"]
    assert flagged["axial_mm"] is not None and flagged["angle_deg"] is not None
    assert flagged["method"] == "multipath" and flagged["sensor_faults"] == []
    strongest = flagged["defects"][0]
    assert strongest["di"] > flagged["threshold"] and strongest["severity"] > 0
    region = strongest["region"]  # the gateway's 90 % localization region, stored with the defect
    assert region["coverage"] == 0.9 and region["axial_half_mm"] > 0 and region["circumferential_half_mm"] > 0
    assert flagged["baseline_measurement_id"] is not None and abs(flagged["stretch"]) < 0.01


def test_detection_pages_follow_cursors_without_repeats(viewer):
    everything = viewer.get("/api/v1/detections", params={"node_id": QUIET_NODES[1], "limit": 1000}).json()["items"]
    seen, cursor = [], None
    for _ in range(100):
        params = {"node_id": QUIET_NODES[1], "limit": 2, **({"cursor": cursor} if cursor else {})}
        page = viewer.get("/api/v1/detections", params=params).json()
        seen += page["items"]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == everything


# ------------------------------------------------------------------ baselines

def test_operator_sets_a_baseline_and_history_keeps_who_when_why(api: Api, operator, viewer):
    node = QUIET_NODES[1]
    before = viewer.get(f"/api/v1/nodes/{node}/baselines").json()
    candidate = viewer.get(f"/api/v1/nodes/{node}/measurements", params={"kind": "monitor", "limit": 1}).json()
    measurement_id = candidate["items"][0]["id"]
    created = operator.post(f"/api/v1/nodes/{node}/baselines",
                            json={"measurement_id": measurement_id, "reason": "pipe re-insulated"})
    assert created.status_code == 201, created.text
    record = created.json()
    assert record["active"] and record["created_by"] == "test-operator" and record["reason"] == "pipe re-insulated"
    history = viewer.get(f"/api/v1/nodes/{node}/baselines").json()
    assert history[0] == record and len(history) == len(before) + 1
    assert not any(b["active"] for b in history[1:])
    assert viewer.get(f"/api/v1/nodes/{node}").json()["active_baseline"] == record
    # Back to the commissioning baseline: a new record naming the same measurement.
    restored = operator.post(f"/api/v1/nodes/{node}/baselines/{before[-1]['id']}/activate",
                             json={"reason": "insulation removed again"})
    assert restored.status_code == 200, restored.text
    assert restored.json()["measurement_id"] == before[-1]["measurement_id"] and restored.json()["active"]


def test_inactive_baseline_candidate_does_not_change_the_active_one(operator, viewer):
    node = QUIET_NODES[0]
    active = viewer.get(f"/api/v1/nodes/{node}").json()["active_baseline"]
    measurement_id = viewer.get(f"/api/v1/nodes/{node}/measurements", params={"limit": 1}).json()["items"][0]["id"]
    created = operator.post(f"/api/v1/nodes/{node}/baselines",
                            json={"measurement_id": measurement_id, "reason": "candidate", "activate": False})
    assert created.status_code == 201 and created.json()["active"] is False
    assert viewer.get(f"/api/v1/nodes/{node}").json()["active_baseline"] == active
    # ... but it joins the node's temperature library: its kind is baseline now
    assert viewer.get(f"/api/v1/measurements/{measurement_id}").json()["kind"] == "baseline"
    library = viewer.get(f"/api/v1/nodes/{node}/measurements", params={"kind": "baseline", "limit": 1000}).json()
    assert measurement_id in [m["id"] for m in library["items"]]


def test_baseline_from_another_nodes_measurement_is_refused(operator, viewer):
    other = latest_monitor_id(viewer, DAMAGED_NODE)
    body = assert_problem(operator.post(f"/api/v1/nodes/{QUIET_NODES[0]}/baselines",
                                        json={"measurement_id": other, "reason": "oops"}), 409, "baseline-refused")
    assert DAMAGED_NODE in body["detail"]
    assert_problem(operator.post(f"/api/v1/nodes/{QUIET_NODES[0]}/baselines",
                                 json={"measurement_id": 999999, "reason": "x"}), 404, "not-found")
    assert_problem(operator.post(f"/api/v1/nodes/{QUIET_NODES[0]}/baselines",
                                 json={"measurement_id": other}), 422, "validation-error")
    assert_problem(operator.post(f"/api/v1/nodes/{QUIET_NODES[0]}/baselines/999999/activate",
                                 json={"reason": "x"}), 404, "not-found")


# ------------------------------------------------------------------ alerts

def test_alerts_list_newest_first_with_the_damage_alert(viewer):
    alerts = viewer.get("/api/v1/alerts", params={"limit": 1000}).json()["items"]
    assert [a["created_at"] for a in alerts] == sorted((a["created_at"] for a in alerts), reverse=True)
    critical = [a for a in alerts if a["severity"] == "critical"]  # the damage alert (payload: alerts/events.py)
    assert critical and {a["node_id"] for a in critical} == {DAMAGED_NODE}
    assert all(a["status"] == "open" for a in alerts)
    by_node = viewer.get("/api/v1/alerts", params={"node_id": DAMAGED_NODE, "severity": "critical"}).json()["items"]
    assert [a["id"] for a in by_node] == [a["id"] for a in alerts
                                         if a["node_id"] == DAMAGED_NODE and a["severity"] == "critical"]


def test_alert_pages_follow_cursors(viewer):
    everything = viewer.get("/api/v1/alerts", params={"limit": 1000}).json()["items"]
    seen, cursor = [], None
    for _ in range(100):
        page = viewer.get("/api/v1/alerts", params={"limit": 1, **({"cursor": cursor} if cursor else {})}).json()
        seen += page["items"]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert [a["id"] for a in seen] == [a["id"] for a in everything]
    assert_problem(viewer.get("/api/v1/alerts", params={"cursor": "eyJ4IjoxfQ"}), 400, "invalid-cursor")


def test_operator_acknowledges_then_resolves_an_alert(operator, viewer):
    alert = viewer.get("/api/v1/alerts", params={"severity": "critical", "limit": 1}).json()["items"][0]
    acked = operator.post(f"/api/v1/alerts/{alert['id']}/acknowledge")
    assert acked.status_code == 200, acked.text
    assert acked.json()["status"] == "acknowledged" and acked.json()["acknowledged_by"] == "test-operator"
    again = operator.post(f"/api/v1/alerts/{alert['id']}/acknowledge").json()
    assert again["acknowledged_at"] == acked.json()["acknowledged_at"]  # idempotent: the first one is kept
    open_ids = [a["id"] for a in viewer.get("/api/v1/alerts", params={"status": "open", "limit": 1000}).json()["items"]]
    assert alert["id"] not in open_ids
    resolved = operator.post(f"/api/v1/alerts/{alert['id']}/resolve").json()
    assert resolved["status"] == "resolved" and resolved["resolved_by"] == "test-operator"
    assert viewer.get(f"/api/v1/alerts/{alert['id']}").json() == resolved
    listed = viewer.get("/api/v1/alerts", params={"status": "resolved"}).json()["items"]
    assert [a["id"] for a in listed] == [alert["id"]]
    assert_problem(operator.post(f"/api/v1/alerts/{uuid.uuid4()}/acknowledge"), 404, "not-found")
    assert_problem(operator.post("/api/v1/alerts/not-a-uuid/resolve"), 422, "validation-error")


# ------------------------------------------------------------------ keys

def test_admin_creates_lists_and_revokes_keys_and_a_revoked_key_stops_working(api: Api, admin):
    created = admin.post("/api/v1/keys", json={"name": "grafana", "role": "viewer"})
    assert created.status_code == 201, created.text
    key = created.json()
    assert key["token"].startswith(key["key_prefix"]) and key["role"] == "viewer"
    listed = admin.get("/api/v1/keys").json()
    assert key["id"] in [k["id"] for k in listed] and all("token" not in k for k in listed)
    with api.client(key["token"]) as new_client:
        assert new_client.get("/api/v1/nodes").status_code == 200
        revoked = admin.delete(f"/api/v1/keys/{key['id']}")
        assert revoked.status_code == 200 and revoked.json()["revoked_at"] is not None
        assert_problem(new_client.get("/api/v1/nodes"), 401, "unauthorized")
    assert_problem(admin.delete("/api/v1/keys/999999"), 404, "not-found")
    assert_problem(admin.post("/api/v1/keys", json={"name": "x", "role": "root"}), 422, "validation-error")


# ------------------------------------------------------------------ node administration (admin)

def test_admin_labels_a_node_and_the_change_records_who_and_when(admin, viewer):
    response = admin.patch(f"/api/v1/nodes/{QUIET_NODES[0]}", json={"label": "Line 3 east", "location": "rack 2"})
    assert response.status_code == 200, response.text
    details = viewer.get(f"/api/v1/nodes/{QUIET_NODES[0]}").json()["details"]
    assert (details["label"], details["location"], details["notes"]) == ("Line 3 east", "rack 2", None)
    assert details["updated_by"] == "test-admin" and details["updated_at"]
    cleared = admin.patch(f"/api/v1/nodes/{QUIET_NODES[0]}", json={"location": None}).json()["details"]
    assert (cleared["label"], cleared["location"]) == ("Line 3 east", None)
    assert_problem(admin.patch(f"/api/v1/nodes/{QUIET_NODES[0]}", json={}), 422, "validation-error")
    assert_problem(admin.patch(f"/api/v1/nodes/{QUIET_NODES[0]}", json={"state": "ok"}), 422, "validation-error")
    assert_problem(admin.patch("/api/v1/nodes/no-such-node", json={"label": "x"}), 404, "not-found")


def test_a_decommissioned_node_leaves_the_fleet_and_its_metrics_until_recommissioned(admin, viewer):
    node = QUIET_NODES[1]
    response = admin.post(f"/api/v1/nodes/{node}/decommission", json={"reason": "line removed"})
    assert response.status_code == 200, response.text
    assert response.json()["decommissioned"]["by"] == "test-admin"
    assert response.json()["health"]["online"] is False
    try:
        assert node not in [n["node_id"] for n in viewer.get("/api/v1/nodes").json()]
        everyone = viewer.get("/api/v1/nodes", params={"include_decommissioned": "true"}).json()
        retired = next(n for n in everyone if n["node_id"] == node)
        assert retired["decommissioned"]["reason"] == "line removed"
        assert viewer.get(f"/api/v1/nodes/{node}/measurements").status_code == 200  # its history stays
        assert f'node="{node}"' not in viewer.get("/metrics").text
        again = admin.post(f"/api/v1/nodes/{node}/decommission", json={"reason": "twice"})
        assert_problem(again, 409, "conflict")
    finally:
        back = admin.post(f"/api/v1/nodes/{node}/recommission")
    assert back.status_code == 200 and back.json()["decommissioned"] is None
    assert node in [n["node_id"] for n in viewer.get("/api/v1/nodes").json()]
    assert_problem(admin.post(f"/api/v1/nodes/{node}/recommission"), 409, "conflict")


# ------------------------------------------------------------------ health, metrics, errors

def test_healthz_and_readyz_answer_without_a_key(api: Api):
    with api.client() as anonymous:
        assert anonymous.get("/healthz").json() == {"status": "ok"}
        ready = anonymous.get("/readyz").json()
        assert ready["status"] == "ready" and ready["schema_revision"]


def test_metrics_expose_per_node_state_di_and_link_counters(viewer):
    response = viewer.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    text = response.text
    assert f'pipesentry_node_state{{node="{DAMAGED_NODE}",state="damage"}} 1.0' in text
    for node in ALL_NODES:
        assert f'pipesentry_node_up{{node="{node}"}}' in text
        assert f'pipesentry_node_di_peak{{node="{node}"}}' in text
        assert f'pipesentry_node_di_threshold{{node="{node}"}}' in text
        assert f'pipesentry_node_last_measurement_timestamp_seconds{{node="{node}"}}' in text
        assert f'pipesentry_node_link_events_total{{counter="node_crc_errors",node="{node}"}} 0.0' in text
        assert f'pipesentry_node_faulty_receivers{{node="{node}"}} 0.0' in text
    assert "pipesentry_database_up 1.0" in text
    assert 'pipesentry_build_info{python_version="' in text and 'version="' in text


def test_unknown_route_and_wrong_method_are_problems(viewer):
    assert_problem(viewer.get("/api/v1/pipes"), 404, "not-found")
    assert_problem(viewer.delete("/api/v1/nodes"), 405, "method-not-allowed")


def test_malformed_json_body_is_a_422_problem(operator):
    response = operator.post(f"/api/v1/nodes/{DAMAGED_NODE}/baselines", content=b"{not json",
                             headers={"Content-Type": "application/json"})
    assert_problem(response, 422, "validation-error")


def test_api_responses_are_not_cached_and_not_sniffed(viewer):
    response = viewer.get("/api/v1/nodes")
    assert response.headers["cache-control"] == "no-store"
    assert response.headers["x-content-type-options"] == "nosniff"



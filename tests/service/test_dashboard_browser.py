"""The dashboard in headless Chromium against the running API on the gateway-filled fleet.

The browser and an offline page come from tests/support/browser_fixtures.py (skips without
Chromium, fails instead with CI=true).
"""
from __future__ import annotations

import pytest

from tests.support.api_fixtures import DAMAGED_NODE, QUIET_NODES, Api

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.timeout(180)]

WAIT_MS = 30_000


def test_damaged_node_shows_as_damaged_with_its_map_and_marked_defect(api: Api, page):
    page.goto(f"{api.base_url}/#key={api.keys.viewer}")
    row_state = page.locator(f'#fleet-table tr[data-node="{DAMAGED_NODE}"] .state')
    row_state.wait_for(timeout=WAIT_MS)
    assert row_state.inner_text() == "damage"
    card = page.locator(f'.node-card[data-node="{DAMAGED_NODE}"]')
    assert "damage" in card.get_attribute("class")
    heatmap = card.locator("img.heatmap")
    page.wait_for_function(
        "img => img.complete && img.naturalWidth > 0", arg=heatmap.element_handle(), timeout=WAIT_MS
    )
    assert heatmap.is_visible()
    latest = api.client(api.keys.viewer).get(f"/api/v1/nodes/{DAMAGED_NODE}/detections/latest").json()
    assert heatmap.get_attribute("data-measurement-id") == str(latest["measurement_id"])
    estimate = card.locator(".estimate")
    assert estimate.is_visible()
    assert f"{latest['axial_mm']:.0f} mm" in estimate.inner_text()
    assert f"{latest['angle_deg']:.0f}°" in estimate.inner_text()
    assert card.locator("svg.trend polyline.peak").count() == 1
    assert card.locator("svg.trend polyline.threshold").count() == 1
    assert "Baseline in use: measurement" in card.locator(".baseline").inner_text()
    # The key went into local storage and out of the address bar.
    assert "key=" not in page.url


def test_quiet_nodes_are_not_shown_damaged(api: Api, page):
    page.goto(f"{api.base_url}/#key={api.keys.viewer}")
    for node in QUIET_NODES:
        state = page.locator(f'#fleet-table tr[data-node="{node}"] .state')
        state.wait_for(timeout=WAIT_MS)
        assert state.inner_text() != "damage"


def test_without_a_key_the_page_asks_for_one_and_then_loads(api: Api, page):
    page.goto(f"{api.base_url}/")
    page.locator("#key-form").wait_for(state="visible", timeout=WAIT_MS)
    page.fill("#key-input", "psk_wrong")
    page.click("#key-form button[type=submit]")
    page.locator("#key-error").wait_for(state="visible", timeout=WAIT_MS)
    assert "refused" in page.locator("#key-error").inner_text()
    page.fill("#key-input", api.keys.viewer)
    page.click("#key-form button[type=submit]")
    page.locator(f'#fleet-table tr[data-node="{DAMAGED_NODE}"]').wait_for(timeout=WAIT_MS)
    assert page.locator("#key-form").is_hidden()


def test_a_labelled_node_shows_its_label_and_a_decommissioned_one_is_gone(api: Api, page):
    with api.client(api.keys.admin) as admin:
        assert admin.patch(f"/api/v1/nodes/{QUIET_NODES[0]}", json={"label": "Line 3 east"}).status_code == 200
        assert admin.post(f"/api/v1/nodes/{QUIET_NODES[1]}/decommission", json={"reason": "removed"}).status_code == 200
        try:
            page.goto(f"{api.base_url}/#key={api.keys.viewer}")
            labelled = page.locator(f'#fleet-table tr[data-node="{QUIET_NODES[0]}"]')
            labelled.wait_for(timeout=WAIT_MS)
            assert f"Line 3 east ({QUIET_NODES[0]})" in labelled.inner_text()
            assert page.locator(f'#fleet-table tr[data-node="{QUIET_NODES[1]}"]').count() == 0
            assert page.locator(f'.node-card[data-node="{QUIET_NODES[1]}"]').count() == 0
        finally:
            assert admin.post(f"/api/v1/nodes/{QUIET_NODES[1]}/recommission").status_code == 200
        # While the page is open: back at the next refresh, and gone again after a decommissioning.
        back = page.locator(f'.node-card[data-node="{QUIET_NODES[1]}"]')
        back.wait_for(timeout=WAIT_MS)
        assert admin.post(f"/api/v1/nodes/{QUIET_NODES[1]}/decommission", json={"reason": "again"}).status_code == 200
        try:
            back.wait_for(state="detached", timeout=WAIT_MS)
        finally:
            assert admin.post(f"/api/v1/nodes/{QUIET_NODES[1]}/recommission").status_code == 200


def test_a_blind_node_says_why_and_a_faulty_receiver_is_named_while_the_others_still_load(api: Api, page):
    import json
    import sqlite3

    blind, faulty = QUIET_NODES
    reason = "the record is stretched +0.23% against the closest baseline (about 23 degC in steel)"
    fault = {"rx_index": 3, "rx_angle_deg": 67.5, "kind": "no_signal", "amplitude_ratio": 0.02, "delay_s": 0.0}
    with sqlite3.connect(api.db_url.removeprefix("sqlite:///")) as db:  # the module's own copy
        latest = "SELECT max(id) FROM detections WHERE node_id = ?"
        db.execute(f"UPDATE detections SET peak_di = NULL, abstain_reason = ?, state = 'no_valid_baseline' "
                   f"WHERE id = ({latest})", (reason, blind))
        db.execute("UPDATE nodes SET state = 'no_valid_baseline', latest_di_peak = NULL WHERE node_id = ?", (blind,))
        db.execute(f"UPDATE detections SET sensor_faults = ? WHERE id = ({latest})", (json.dumps([fault]), faulty))
    page.goto(f"{api.base_url}/#key={api.keys.viewer}")
    blind_notice = page.locator(f'.node-card[data-node="{blind}"] .notice')
    blind_notice.wait_for(state="visible", timeout=WAIT_MS)
    assert f"Not assessed: {reason}" in blind_notice.inner_text()
    assert page.locator(f'.node-card[data-node="{blind}"] img.heatmap').is_hidden()
    fault_notice = page.locator(f'.node-card[data-node="{faulty}"] .notice')
    fault_notice.wait_for(state="visible", timeout=WAIT_MS)
    assert "Receivers left out of the map: 3 at 68° (no signal)" in fault_notice.inner_text()
    damaged_map = page.locator(f'.node-card[data-node="{DAMAGED_NODE}"] img.heatmap')
    page.wait_for_function("img => img.complete && img.naturalWidth > 0", arg=damaged_map.element_handle(),
                           timeout=WAIT_MS)
    assert "refresh failed" not in page.locator("#status").inner_text()


def _alarm_share(png: bytes) -> float:
    """Share of the map area's pixels in alarm colours (saturated hues); the colour bar is left out."""
    import io

    import numpy as np
    from matplotlib.colors import rgb_to_hsv
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float) / 255.0
    height, width, _ = rgb.shape
    area = rgb[int(0.15 * height):int(0.85 * height), int(0.15 * width):int(0.65 * width)]
    hsv = rgb_to_hsv(area)
    return float(np.mean((hsv[..., 1] > 0.35) & (hsv[..., 2] > 0.2)))


def test_a_healthy_nodes_map_is_calm_and_a_damaged_ones_unmistakable(api: Api):
    with api.client(api.keys.viewer) as client:
        shares = {}
        for node in (QUIET_NODES[0], DAMAGED_NODE):
            latest = client.get(f"/api/v1/nodes/{node}/detections/latest").json()
            png = client.get(f"/api/v1/measurements/{latest['measurement_id']}/di-maps/gateway.png")
            assert png.status_code == 200
            shares[node] = _alarm_share(png.content)
    assert shares[QUIET_NODES[0]] < 0.01, shares  # jet filled a sound node's card with colour
    assert shares[DAMAGED_NODE] > 0.03, shares


def test_the_trend_has_a_time_axis_di_ticks_and_the_threshold_from_the_first_calibrated_reading(api: Api, page):
    import sqlite3

    node = QUIET_NODES[0]
    with sqlite3.connect(api.db_url.removeprefix("sqlite:///")) as db:  # as right after calibration
        db.execute("UPDATE detections SET threshold = NULL WHERE node_id = ? AND id < (SELECT max(id) FROM detections "
                   "WHERE node_id = ?)", (node, node))
    page.goto(f"{api.base_url}/#key={api.keys.viewer}")
    trend = page.locator(f'.node-card[data-node="{node}"] svg.trend')
    trend.locator("polyline.peak").wait_for(state="attached", timeout=WAIT_MS)
    assert trend.locator("text.tick-di").count() >= 3
    assert trend.locator("text.tick-time").count() >= 2
    assert all(":" in t for t in trend.locator("text.tick-time").all_text_contents())  # clock times
    threshold = trend.locator("polyline.threshold")
    assert threshold.count() == 1
    box = threshold.bounding_box()
    assert box is not None and box["width"] > 5, "one calibrated reading draws no threshold line"

"""The dashboard of a central site with 1,000 nodes, in headless Chromium: sites first, then one page
of nodes, filters that work, and a bounded number of requests whatever the fleet size."""
from __future__ import annotations

from collections.abc import Iterator
from urllib.parse import urlsplit

import pytest

from tests.support.central_site import Centre, serve_centre
from tests.support.ingest_batches import batch_of, detection_record, measurement_record, node_record
from uplink.contract import Record

pytestmark = [pytest.mark.browser, pytest.mark.e2e, pytest.mark.timeout(180)]

WAIT_MS = 30_000
DAMAGED = [f"s-{i:04d}" for i in (7, 77, 177, 277, 377)]


def nodes(gateway: str, prefix: str, count: int) -> list[Record]:
    return [node_record(gateway, f"{prefix}-{i:04d}") for i in range(count)]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Iterator[Centre]:
    url = f"sqlite:///{tmp_path_factory.mktemp('fleet1000') / 'central.db'}"
    with serve_centre(url) as centre:
        batches = [batch_of("gw-n1", "north", nodes("gw-n1", "n", 400)),
                   batch_of("gw-n2", "north", nodes("gw-n2", "m", 200)),
                   batch_of("gw-s1", "south", nodes("gw-s1", "s", 400))]
        flagged: list[Record] = []
        for local_id, node_id in enumerate(DAMAGED, start=1):
            flagged += [node_record("gw-s1", node_id, state="damage"),
                        measurement_record("gw-s1", node_id, local_id, traces=False, with_map=True),
                        detection_record("gw-s1", node_id, local_id, local_id, state="damage")]
        batches.append(batch_of("gw-s1", "south", flagged))
        for batch in batches:
            key = centre.north if batch.site == "north" else centre.south
            assert centre.post(batch, key).status_code == 200
        yield centre


def rows(page) -> list[str]:
    return page.locator("#fleet-table tbody tr").evaluate_all("rows => rows.map(r => r.dataset.node)")


def test_a_thousand_nodes_load_sites_first_then_a_page_and_filter(fleet: Centre, page):
    api_requests: list[str] = []
    page.on("request", lambda r: api_requests.append(r.url) if urlsplit(r.url).path.startswith("/api/") else None)
    page.goto(f"{fleet.url}/#key={fleet.viewer}")
    page.locator("#sites-table tbody tr").first.wait_for(timeout=WAIT_MS)
    sites = page.locator("#sites-table tbody tr").evaluate_all("rows => rows.map(r => r.innerText)")
    assert len(sites) == 2 and sites[0].startswith("south") and "gw-s1" in sites[0] and "400" in sites[0]
    assert "5 / 0" in sites[0] and sites[1].startswith("north") and "600" in sites[1]
    page.wait_for_function("() => document.querySelectorAll('#fleet-table tbody tr').length === 100", timeout=WAIT_MS)
    assert "1000 node(s) at 2 site(s), 5 damaged" in page.locator("#status").inner_text()
    assert page.locator("#next-page").is_visible()
    # Only the flagged nodes of the page get a card (with its trend and map): not one per node.
    page.wait_for_function("() => document.querySelectorAll('.node-card').length === 0", timeout=WAIT_MS)
    first_load = len(api_requests)
    assert first_load <= 4, api_requests  # sites, one page of nodes (no flagged node among n-0000..n-0099)

    page.select_option("#state-filter", "damage")
    page.wait_for_function("() => document.querySelectorAll('#fleet-table tbody tr').length === 5", timeout=WAIT_MS)
    assert rows(page) == DAMAGED
    assert page.locator("#fleet-table tbody tr").first.inner_text().count("south / gw-s1") == 1
    page.locator(f'.node-card[data-node="{DAMAGED[0]}"] img.heatmap').wait_for(timeout=WAIT_MS)
    assert page.locator(".node-card").count() == 5
    assert len(api_requests) - first_load <= 2 + 5 * 2  # sites, the page, and per card its trend and map

    page.select_option("#state-filter", "")
    page.locator('#sites-table tbody tr[data-site="north"]').click()
    page.wait_for_function("() => document.querySelector('#site-filter').value === 'north'", timeout=WAIT_MS)
    page.wait_for_function("() => document.querySelector('#fleet-table tbody tr').dataset.node === 'm-0000'",
                           timeout=WAIT_MS)
    first_page = rows(page)
    page.click("#next-page")
    page.wait_for_function("() => document.querySelector('#fleet-table tbody tr').dataset.node === 'm-0100'",
                           timeout=WAIT_MS)
    assert len(rows(page)) == 100 and not set(rows(page)) & set(first_page)
    assert "page 2" in page.locator("#page-info").inner_text()

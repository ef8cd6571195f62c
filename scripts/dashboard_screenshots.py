#!/usr/bin/env python3
"""Refresh docs/images/dashboard-*.png: the dashboard's cards of a healthy, a suspected, a damaged and a
blind node, in headless Chromium, from a real fleet (mock nodes and the gateway, as `make demo` runs).

    .venv/bin/python scripts/dashboard_screenshots.py [--out docs/images] [--keep DIR]

Every state is reached by the physics, not written into the database: a quiet node (ok); a notch
with a hysteresis of 100 readings, more than the run lasts (suspected); a notch with M = 2 (damage); a
temperature swing of 30 degC with the library's growth off, so that every baseline is soon
beyond the compensated range (no_valid_baseline). About a minute on the 2-core machine.
"""
from __future__ import annotations

import argparse
import io
import shutil
import sys
import tempfile
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from db.api_keys import create_api_key  # noqa: E402
from db.database import open_database  # noqa: E402
from db.models import NodeRow, Role  # noqa: E402
from service.settings import ApiSettings  # noqa: E402
from tests.support.api_fixtures import ApiServer  # noqa: E402
from tests.support.browser_fixtures import CHROMIUM_ARGS, chromium_path  # noqa: E402
from tests.support.process_harness import (  # noqa: E402
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

DEFECT = (200.0, 90.0, 20.0)  # axial_mm, angle_deg, appears_at_s: after commissioning and calibration
NODES = {  # node id -> (state it must reach, scenario node, gateway settings overrides)
    "healthy": ("ok", {}, {}),
    "suspected": ("suspected", {"defect": DEFECT}, {"threshold": {"calibration_count": 8, "hysteresis_count": 100}}),
    "damaged": ("damage", {"defect": DEFECT}, {}),
    "blind": ("no_valid_baseline",
              {"temperature": {"mean_c": 21.0, "daily_amplitude_c": 30.0, "period_s": 240.0, "jitter_c": 0.02}},
              {"imaging": {"library_temperature_step_c": 0.0}}),
}
FLEET_TIMEOUT_S = 180.0
VIEWPORT = {"width": 1280, "height": 1800}


def _scenario() -> str:
    return "".join(scenario_node(node, 500 + i, **spec) for i, (node, (_, spec, _)) in enumerate(NODES.items()))


def _states(url: str) -> dict[str, str]:
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            return {n.node_id: n.state.value for n in session.query(NodeRow).all()}
    finally:
        database.dispose()


def build_fleet(run_dir: Path) -> Path:
    """Run the four nodes until each is in its state; returns the database file (the gateway stopped)."""
    scenario = run_dir / "scenario.toml"
    scenario.write_text(_scenario())
    links = run_dir / "links"
    mock = start_mock_nodes(scenario, links, run_dir)
    try:
        wait_for_links(links, list(NODES), mock)
        db_path = run_dir / "fleet.db"
        nodes = []
        for node, (_, _, overrides) in NODES.items():
            settings = gateway_node(node, links, interval_s=0.5)
            for table, values in overrides.items():
                settings[table] = {**settings.get(table, {}), **values}
            nodes.append(settings)
        config = run_dir / "gateway.toml"
        config.write_text(gateway_config(db_path, nodes))
        gateway = start_gateway(config, run_dir)
        try:
            wanted = {node: state for node, (state, _, _) in NODES.items()}

            def reached() -> bool:
                if not gateway.alive():
                    raise SystemExit(f"the gateway exited: {gateway.stderr[-2000:]}")
                return _states(f"sqlite:///{db_path}") == wanted

            wait_until(reached, FLEET_TIMEOUT_S, 0.5, what=f"the nodes in the states {wanted}")
        finally:
            gateway.terminate()
            gateway.close()
    finally:
        mock.close()
    return db_path


def _key(url: str, role: Role) -> str:
    database = open_database(url, upgrade=False)
    try:
        with database.write() as session:
            return create_api_key(session, name=f"screenshots-{role.value}", role=role)[1]
    finally:
        database.dispose()


def _small_png(png: bytes) -> bytes:
    """A palette PNG (256 colours): a fifth of the size, indistinguishable for a page like this."""
    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return out.getvalue()


def screenshot_cards(db_path: Path, out_dir: Path) -> list[Path]:
    from playwright.sync_api import sync_playwright

    url = f"sqlite:///{db_path}"
    key, admin = _key(url, Role.VIEWER), _key(url, Role.ADMIN)
    chromium = chromium_path()
    if chromium is None:
        raise SystemExit("headless Chromium is needed: bash scripts/ensure-chromium.sh")
    written = []
    with ApiServer(ApiSettings(database_url=url)) as server, sync_playwright() as playwright:
        for node in NODES:  # a label, as an admin sets it
            answer = httpx.patch(f"{server.base_url}/api/v1/nodes/{node}", json={"label": f"Example: {node} node"},
                                 headers={"Authorization": f"Bearer {admin}"}, timeout=10)
            answer.raise_for_status()
        browser = playwright.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(f"{server.base_url}/#key={key}")
            for node, (state, _, _) in NODES.items():
                card = page.locator(f'.node-card[data-node="{node}"]')
                card.wait_for(timeout=30_000)
                page.wait_for_function("c => c.querySelector('.trend polyline.peak, .trend text')",
                                       arg=card.element_handle(), timeout=30_000)
                if state != "no_valid_baseline":
                    page.wait_for_function("img => img.complete && img.naturalWidth > 0",
                                           arg=card.locator("img.heatmap").element_handle(), timeout=30_000)
                target = out_dir / f"dashboard-{node}.png"
                target.write_bytes(_small_png(card.screenshot()))
                written.append(target)
            fleet = out_dir / "dashboard-fleet.png"
            fleet.write_bytes(_small_png(page.locator("#fleet").screenshot()))
            written.append(fleet)
        finally:
            browser.close()
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--keep", type=Path, help="build the fleet in this directory and keep it (logs, database)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    run_dir = args.keep or Path(tempfile.mkdtemp(prefix="ps-screens-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        for path in screenshot_cards(build_fleet(run_dir), args.out):
            print(f"{path.relative_to(REPO) if path.is_relative_to(REPO) else path}: {path.stat().st_size // 1024} KiB")
    finally:
        if args.keep is None:
            shutil.rmtree(run_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""An operator's changes at a gateway reach the centre (issue 17, a replication gap): a real gateway
process polling a mock node over a pty replicates to a real central service (uvicorn on 127.0.0.1 over
a SQLite file); the gateway's own API (uvicorn on 127.0.0.1 over the gateway's database, another
process's writes) sets a new active baseline and decommissions the node. The centre's API then shows
the new baseline active, the commissioning one deactivated, and the node decommissioned (by whom and
why) — though the decommissioned node has no more cycles to carry it.
"""
from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import httpx
import pytest
from sqlalchemy import select

from db.api_keys import create_api_key
from db.database import open_database
from db.models import IngestedRecordRow, MeasurementKind, MeasurementRow, Role
from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer
from tests.support.central_site import Centre, north_edge, serve_centre
from tests.support.process_harness import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]

GATEWAY, NODE = "gw-n1", "pipe-1"
STEP_TIMEOUT_S = 30.0


def centre_node(centre: Centre) -> dict | None:
    response = centre.get(f"/nodes/{NODE}")
    return response.json() if response.status_code == 200 else None


def central_id(centre: Centre, gateway_measurement_id: int) -> int | None:
    with centre.database.session() as session:
        row = session.get(IngestedRecordRow, f"{GATEWAY}/measurement/{gateway_measurement_id}")
        return None if row is None else int(row.central_id)


def test_a_baseline_set_and_a_decommissioning_at_the_gateways_api_reach_the_centre(tmp_path: Path, sqlite_url: str):
    with serve_centre(sqlite_url) as centre:
        with north_edge(centre, tmp_path, gateway_id=GATEWAY, node_id=NODE, seed=711) as site, ExitStack() as stack:
            wait_until(lambda: centre_node(centre), STEP_TIMEOUT_S, 0.3, what="the node at the centre")
            edge = open_database(f"sqlite:///{site.database_path}", upgrade=False)
            stack.callback(edge.dispose)

            def replicated_monitor() -> int | None:
                with edge.session() as session:
                    ids = session.scalars(select(MeasurementRow.id).where(
                        MeasurementRow.kind == MeasurementKind.MONITOR).order_by(MeasurementRow.id)).all()
                return next((i for i in ids if central_id(centre, i) is not None), None)

            chosen = wait_until(replicated_monitor, STEP_TIMEOUT_S, 0.3, what="a monitor measurement at the centre")
            first = centre_node(centre)
            assert first is not None and first["active_baseline"]["reason"].startswith("commissioning")
            assert first["decommissioned"] is None
            with edge.write() as session:
                admin = create_api_key(session, name="admin-eve", role=Role.ADMIN)[1]

            with ApiServer(ApiSettings(database_url=f"sqlite:///{site.database_path}")) as gateway_api:
                headers = {"Authorization": f"Bearer {admin}"}
                base = f"{gateway_api.base_url}/api/v1/nodes/{NODE}"
                made = httpx.post(f"{base}/baselines", json={"measurement_id": chosen, "reason": "after the repair"},
                                  headers=headers, timeout=10)
                assert made.status_code == 201, made.text
                gone = httpx.post(f"{base}/decommission", json={"reason": "pipe section replaced"},
                                  headers=headers, timeout=10)
                assert gone.status_code == 200, gone.text

            def caught_up() -> dict | None:
                node = centre_node(centre)
                if node is None or node["decommissioned"] is None or node["active_baseline"] is None:
                    return None
                return node if node["active_baseline"]["reason"] == "after the repair" else None

            node = wait_until(caught_up, STEP_TIMEOUT_S, 0.3, what="the baseline and the decommissioning at the centre")
            assert node["active_baseline"]["measurement_id"] == central_id(centre, chosen)
            assert node["active_baseline"]["created_by"] == "admin-eve"
            assert node["decommissioned"]["by"] == "admin-eve"
            assert node["decommissioned"]["reason"] == "pipe section replaced"
            history = centre.get(f"/nodes/{NODE}/baselines").json()
            assert [(b["reason"], b["active"]) for b in history] == [("after the repair", True),
                                                                     ("commissioning: first measurement", False)]
            assert NODE not in [n["node_id"] for n in centre.get("/nodes").json()]  # out of service there too

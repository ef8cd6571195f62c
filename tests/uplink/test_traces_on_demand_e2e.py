"""Raw traces on demand (issue 17): a gateway under ``send = "flagged_traces"`` sends a calm measurement
without its traces; a central operator asks for them, the gateway (which only talks outbound) hears
of it on its next poll and sends them, and the centre adds them to the record it holds, byte for
byte the gateway's. Traces the gateway's retention removed are reported as such.

The real central service (uvicorn on 127.0.0.1 over a SQLite file), a real gateway process polling a
mock node over a pty, the gateway's real retention.
"""
from __future__ import annotations

import hashlib
from contextlib import ExitStack
from datetime import timedelta
from pathlib import Path

import httpx
import pytest
from sqlalchemy.orm import undefer

from db.api_keys import create_api_key
from db.database import open_database
from db.models import MeasurementRow, Role
from db.retention import prune_traces
from tests.support.api_fixtures import assert_problem
from tests.support.central_site import Centre, north_edge, serve_centre
from tests.support.metrics_text import sample
from tests.support.process_harness import gateway_metrics_port, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]

GATEWAY, NODE = "gw-n1", "pipe-1"
STEP_TIMEOUT_S = 30.0


def traces_of(centre: Centre, measurement_id: int) -> dict:
    response = centre.get(f"/measurements/{measurement_id}")
    assert response.status_code == 200, response.text
    return response.json()["traces"]


def sent_without_traces(centre: Centre, count: int) -> list[int] | None:
    """``count`` of the node's measurements at the centre whose traces stayed at the gateway, oldest first."""
    page = centre.get(f"/nodes/{NODE}/measurements", limit=100, order="asc")
    if page.status_code != 200:
        return None
    ids = [m["id"] for m in page.json()["items"] if not m["traces_available"]]
    return ids[:count] if len(ids) >= count else None


def ask(centre: Centre, key: str, measurement_id: int) -> httpx.Response:
    return httpx.post(f"{centre.url}/api/v1/measurements/{measurement_id}/traces/request", timeout=10,
                      headers={"Authorization": f"Bearer {key}"})


def test_an_operator_gets_the_traces_of_an_unflagged_measurement_and_hears_when_they_are_gone(
    tmp_path: Path, sqlite_url: str,
):
    with serve_centre(sqlite_url) as centre:
        with centre.database.write() as session:
            operator = create_api_key(session, name="operator-ana", role=Role.OPERATOR)[1]
        with (north_edge(centre, tmp_path, gateway_id=GATEWAY, node_id=NODE, seed=710, send="flagged_traces",
                        requests_every_s=0.3) as site, ExitStack() as stack):
            wanted, gone = wait_until(lambda: sent_without_traces(centre, 2), STEP_TIMEOUT_S, 0.3,
                                      what="two calm measurements at the centre without their traces")
            assert traces_of(centre, wanted)["status"] == "at_gateway"
            assert ask(centre, centre.viewer, wanted).status_code == 403  # a viewer reads, an operator asks

            asked = ask(centre, operator, wanted)
            assert asked.status_code == 202, asked.text
            assert asked.json()["status"] == "requested" and asked.json()["requested_by"] == "operator-ana"
            wait_until(lambda: traces_of(centre, wanted)["status"] == "received", STEP_TIMEOUT_S, 0.2,
                       what="the requested traces at the centre")
            state = traces_of(centre, wanted)
            assert state["gateway_id"] == GATEWAY and state["answered_at"] and state["received_at"]
            local_id = int(state["measurement_uid"].rsplit("/", 1)[1])
            edge = open_database(f"sqlite:///{site.database_path}", upgrade=False)
            stack.callback(edge.dispose)
            with edge.session() as session, centre.database.session() as central:
                at_gateway = session.get(MeasurementRow, local_id, options=[undefer(MeasurementRow.traces_blob)])
                here = central.get(MeasurementRow, wanted, options=[undefer(MeasurementRow.traces_blob)])
                assert at_gateway is not None and here is not None and at_gateway.traces_blob is not None
                assert here.traces_blob == at_gateway.traces_blob
                assert here.traces_sha256 == at_gateway.traces_sha256
            assert centre.get(f"/measurements/{wanted}/traces", units="codes").status_code == 200
            assert ask(centre, operator, wanted).status_code == 200  # here now: nothing to ask

            # The gateway's retention removes the other calm measurement's traces; asking for them says so.
            assert prune_traces(edge.write, timedelta(0), 100) >= 1
            assert ask(centre, operator, gone).status_code == 202
            wait_until(lambda: traces_of(centre, gone)["status"] == "pruned", STEP_TIMEOUT_S, 0.2,
                       what="the gateway's answer that the traces are gone")
            body = assert_problem(ask(centre, operator, gone), 410, "traces-pruned")
            assert f"gateway '{GATEWAY}'" in body["detail"] and "no longer holds" in body["detail"]
            assert centre.get(f"/measurements/{gone}/traces").status_code == 410
            metrics = httpx.get(f"http://127.0.0.1:{gateway_metrics_port(site.gateway)}/metrics", timeout=5.0).text
            answered = {answer: sample(metrics, "pipesentry_gateway_uplink_trace_requests_total", answer=answer)
                        for answer in ("held", "pruned")}
            assert answered == {"held": 1.0, "pruned": 1.0}
            assert sample(metrics, "pipesentry_gateway_uplink_trace_request_failures_total") == 0.0


def test_a_resent_record_the_centre_refuses_ends_the_request_refused_with_why_and_loses_no_traces(
    tmp_path: Path, sqlite_url: str,
):
    """The centre's description of a measurement disagrees with the traces its gateway holds (another
    checksum): the gateway answers ``held`` and re-sends them, the centre refuses the record (422),
    and the operator sees the request end ``refused`` with the refusal instead of ``held`` for ever.
    Nothing is taken at the centre, the gateway keeps the traces (its retention too), its queue goes
    on; once the description is put right, asking again brings them, byte for byte."""
    with serve_centre(sqlite_url) as centre:
        with centre.database.write() as session:
            operator = create_api_key(session, name="operator-ana", role=Role.OPERATOR)[1]
        with (north_edge(centre, tmp_path, gateway_id=GATEWAY, node_id=NODE, seed=711, send="flagged_traces",
                        requests_every_s=0.3) as site, ExitStack() as stack):
            [wanted] = wait_until(lambda: sent_without_traces(centre, 1), STEP_TIMEOUT_S, 0.3,
                                  what="a calm measurement at the centre without its traces")
            with centre.database.write() as session:
                row = session.get(MeasurementRow, wanted)
                assert row is not None
                true_sha256, row.traces_sha256 = row.traces_sha256, "0" * 64

            assert ask(centre, operator, wanted).status_code == 202
            wait_until(lambda: traces_of(centre, wanted)["status"] == "refused", STEP_TIMEOUT_S, 0.2,
                       what="the request refused, not held for ever")
            state = traces_of(centre, wanted)
            assert state["answered_at"] and state["refused_at"] and state["received_at"] is None
            assert state["refusal"].startswith("HTTP 422 ingest-bad-record: traces (sha256 ")
            assert "a stored measurement does not change" in state["refusal"]

            local_id = int(state["measurement_uid"].rsplit("/", 1)[1])
            edge = open_database(f"sqlite:///{site.database_path}", upgrade=False)
            stack.callback(edge.dispose)
            port = gateway_metrics_port(site.gateway)

            def newest_at_centre() -> int:
                return int(centre.get(f"/nodes/{NODE}/measurements", limit=1, order="desc").json()["items"][0]["id"])

            def gateway_metric(name: str, **labels: str) -> float:
                return sample(httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5.0).text, name, **labels)

            wait_until(lambda: gateway_metric("pipesentry_gateway_uplink_refused_records") == 1.0, STEP_TIMEOUT_S,
                       0.2, what="the gateway setting the refused record aside")
            newest = wait_until(lambda: newest_at_centre() > wanted + 1 and newest_at_centre(), STEP_TIMEOUT_S, 0.3,
                                what="the node's later records still replicating")
            prune_traces(edge.write, timedelta(0), 100)  # retention keeps what the centre has not got
            with edge.session() as session, centre.database.session() as central:
                at_gateway = session.get(MeasurementRow, local_id, options=[undefer(MeasurementRow.traces_blob)])
                here = central.get(MeasurementRow, wanted, options=[undefer(MeasurementRow.traces_blob)])
                assert at_gateway is not None and at_gateway.traces_blob is not None
                assert hashlib.sha256(at_gateway.traces_blob).hexdigest() == at_gateway.traces_sha256 == true_sha256
                assert here is not None and here.traces_blob is None and here.traces_pruned_at is not None
            assert centre.get(f"/measurements/{wanted}/traces").status_code == 410
            assert traces_of(centre, wanted)["status"] == "refused"  # the gateway's further tries changed nothing
            assert newest_at_centre() >= newest

            # The cause put right: asked again, the request starts over and the traces come.
            with centre.database.write() as session:
                row = session.get(MeasurementRow, wanted)
                assert row is not None
                row.traces_sha256 = true_sha256
            again = ask(centre, operator, wanted)
            assert again.status_code == 202 and again.json()["status"] == "requested"
            assert again.json()["refusal"] is None
            wait_until(lambda: traces_of(centre, wanted)["status"] == "received", STEP_TIMEOUT_S, 0.2,
                       what="the traces asked for again")
            with edge.session() as session, centre.database.session() as central:
                at_gateway = session.get(MeasurementRow, local_id, options=[undefer(MeasurementRow.traces_blob)])
                here = central.get(MeasurementRow, wanted, options=[undefer(MeasurementRow.traces_blob)])
                assert at_gateway is not None and here is not None and here.traces_blob == at_gateway.traces_blob
            assert gateway_metric("pipesentry_gateway_uplink_trace_requests_total", answer="held") == 2.0

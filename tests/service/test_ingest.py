"""The central site's ingest: a gateway's batch is stored whole or refused whole, each record once.

A real API server (uvicorn on 127.0.0.1) over a fresh SQLite file, and over PostgreSQL for the
concurrent replay; the batches are built with the wire contract the gateways use.
"""
from __future__ import annotations

import base64
import gzip
import json
import threading
from collections.abc import Iterator
from datetime import timedelta

import httpx
import pytest
from sqlalchemy import select

from db.models import BaselineRow, DeliveryRow, DetectionRow, DiMapRow, EventRow, MeasurementRow, NodeRow
from tests.support.api_fixtures import assert_problem
from tests.support.central_site import Centre, serve_centre
from tests.support.db_fixtures import T0
from tests.support.ingest_batches import (
    alert_record,
    baseline_record,
    batch_of,
    detection_record,
    measurement_record,
    node_history,
    node_record,
    state_change_record,
)


@pytest.fixture
def centre(sqlite_url: str) -> Iterator[Centre]:
    with serve_centre(sqlite_url) as serving:
        yield serving


def test_a_batch_is_stored_and_its_replay_duplicates_nothing(centre: Centre):
    batch = batch_of("gw-n1", "north", [*node_history("gw-n1", "pipe-1", 1, 3, with_map=True),
                                        state_change_record("gw-n1", "pipe-1", 1, 3)])
    first = centre.post(batch, centre.north)
    assert first.status_code == 200, first.text
    assert first.json() == {"batch_id": str(batch.batch_id), "accepted": 8, "duplicates": 0, "stale": 0}
    counts = [centre.count(m) for m in (NodeRow, MeasurementRow, DiMapRow, DetectionRow)]
    assert counts == [1, 3, 3, 3]

    again = centre.post(batch, centre.north)  # a retry after a lost answer
    assert again.json() == {"batch_id": str(batch.batch_id), "accepted": 0, "duplicates": 8, "stale": 0}
    assert [centre.count(m) for m in (NodeRow, MeasurementRow, DiMapRow, DetectionRow)] == counts
    with centre.database.session() as session:
        node = session.get(NodeRow, "pipe-1")
        assert (node.site, node.gateway_id) == ("north", "gw-n1")
        stored = session.scalars(select(MeasurementRow).order_by(MeasurementRow.id)).all()
        assert [m.traces_sha256 for m in stored] == [r.traces.sha256 for r in batch.records[1:7:2]]  # type: ignore[union-attr]
        assert stored[0].traces_blob == batch.records[1].traces.raw()  # type: ignore[union-attr]


def test_a_later_batch_may_refer_to_records_of_an_earlier_one(centre: Centre):
    first = [node_record("gw-n1", "pipe-1"), measurement_record("gw-n1", "pipe-1", 1),
             measurement_record("gw-n1", "pipe-1", 2)]
    assert centre.post(batch_of("gw-n1", "north", first), centre.north).status_code == 200
    later = [detection_record("gw-n1", "pipe-1", 1, 2), state_change_record("gw-n1", "pipe-1", 1, 2)]
    assert centre.post(batch_of("gw-n1", "north", later), centre.north).json()["accepted"] == 2
    with centre.database.session() as session:
        detection = session.scalars(select(DetectionRow)).one()
        assert session.get(MeasurementRow, detection.measurement_id).node_measurement_id == 2
    # A second verdict on the same measurement under another uid is refused, naming it.
    twice = centre.post(batch_of("gw-n1", "north", [detection_record("gw-n1", "pipe-1", 2, 2)]), centre.north)
    body = assert_problem(twice, 422, "ingest-bad-record")
    assert body["bad_record"]["uid"] == "gw-n1/detection/2" and "already has a detection" in body["detail"]


def test_traces_not_sent_are_stored_as_unavailable_with_their_checksum(centre: Centre):
    batch = batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 1, traces=False))
    assert centre.post(batch, centre.north).status_code == 200
    with centre.database.session() as session:
        row = session.scalars(select(MeasurementRow)).one()
        assert row.traces_blob is None and row.traces_pruned_at is not None
        assert row.traces_sha256 == batch.records[1].traces.sha256  # type: ignore[union-attr]


def test_a_malformed_batch_is_refused_whole_naming_the_bad_record(centre: Centre):
    batch = batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 2))
    raw = batch.model_dump(mode="json")
    raw["records"][3]["settings"]["n_samples"] = -5

    refused = centre.post(json.dumps(raw).encode(), centre.north)
    body = assert_problem(refused, 422, "ingest-bad-record")
    assert body["bad_record"] == {"index": 3, "uid": "gw-n1/measurement/2", "kind": "measurement",
                                  "error": "settings.n_samples: Input should be greater than or equal to 1"}
    assert [centre.count(m) for m in (NodeRow, MeasurementRow)] == [0, 0]


def test_a_record_refused_by_the_database_leaves_nothing_of_its_batch(centre: Centre):
    # The detection names a measurement the centre never received: the records before it go too.
    batch = batch_of("gw-n1", "north", [*node_history("gw-n1", "pipe-1", 1, 2),
                                        detection_record("gw-n1", "pipe-1", 50, 7)])
    body = assert_problem(centre.post(batch, centre.north), 409, "ingest-unknown-reference")
    assert body["bad_record"]["index"] == 5 and body["bad_record"]["uid"] == "gw-n1/detection/50"
    assert "gw-n1/measurement/7" in body["detail"]
    assert [centre.count(m) for m in (NodeRow, MeasurementRow, DetectionRow)] == [0, 0, 0]


def test_one_gateway_cannot_overwrite_another_gateways_nodes(centre: Centre):
    assert centre.post(batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 1)), centre.north).status_code == 200
    # The south gateway claims pipe-1 under its own name and site: refused, pipe-1 unchanged.
    hijack = batch_of("gw-s1", "south", [node_record("gw-s1", "pipe-1", state="damage"),
                                         measurement_record("gw-s1", "pipe-1", 1)])
    body = assert_problem(centre.post(hijack, centre.south), 403, "forbidden")
    assert body["bad_record"]["index"] == 0
    assert "belongs to gateway 'gw-n1' of site 'north'" in body["detail"]
    # Another gateway of the same site may not either; and no key writes for another site.
    same_site = batch_of("gw-n2", "north", [node_record("gw-n2", "pipe-1", state="damage")])
    assert_problem(centre.post(same_site, centre.north), 403, "forbidden")
    other_site = batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-9")])
    body = assert_problem(centre.post(other_site, centre.south), 403, "forbidden")
    assert "this key writes for site 'south'" in body["detail"]
    with centre.database.session() as session:
        node = session.get(NodeRow, "pipe-1")
        assert (node.gateway_id, node.state.value) == ("gw-n1", "ok")
        assert centre.count(MeasurementRow) == 1 and session.get(NodeRow, "pipe-9") is None


def test_only_gateway_keys_ingest_and_gateway_keys_read_nothing(centre: Centre):
    batch = batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1")])
    assert_problem(centre.post(batch, centre.viewer), 403, "forbidden")
    reading = httpx.get(f"{centre.url}/api/v1/nodes", headers={"Authorization": f"Bearer {centre.north}"})
    assert_problem(reading, 403, "forbidden")


def test_a_node_record_older_than_the_centres_view_is_ignored(centre: Centre):
    newer = node_record("gw-n1", "pipe-1", seen_at=T0 + timedelta(hours=1), state="damage")
    assert centre.post(batch_of("gw-n1", "north", [newer]), centre.north).json()["accepted"] == 1
    older = node_record("gw-n1", "pipe-1", seen_at=T0, state="ok")
    assert centre.post(batch_of("gw-n1", "north", [older]), centre.north).json()["stale"] == 1
    with centre.database.session() as session:
        assert session.get(NodeRow, "pipe-1").state.value == "damage"


def test_a_later_admin_change_wins_over_an_older_node_record_with_the_same_last_seen_at(centre: Centre):
    seen = T0 + timedelta(hours=1)
    assert centre.post(batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1", seen_at=seen, revision=4)]),
                       centre.north).json()["accepted"] == 1
    decommissioned = node_record("gw-n1", "pipe-1", seen_at=seen, revision=5, label="Line 3",
                                 decommissioned_at=seen + timedelta(minutes=5), decommissioned_by="alice",
                                 decommission_reason="pipe replaced")
    assert centre.post(batch_of("gw-n1", "north", [decommissioned]), centre.north).json()["accepted"] == 1
    # The older view again (a replay), even with a later last_seen_at: ignored.
    replay = node_record("gw-n1", "pipe-1", seen_at=seen + timedelta(minutes=1), revision=4)
    assert centre.post(batch_of("gw-n1", "north", [replay]), centre.north).json()["stale"] == 1
    assert centre.post(batch_of("gw-n1", "north", [decommissioned]), centre.north).json()["duplicates"] == 1

    node = centre.get("/nodes/pipe-1").json()
    assert node["details"]["label"] == "Line 3"
    assert node["decommissioned"]["by"] == "alice" and node["decommissioned"]["reason"] == "pipe replaced"
    # Later cycles at the same revision move last_seen_at on: applied.
    later = decommissioned.model_copy(update={"last_seen_at": seen + timedelta(hours=2), "online": False})
    assert centre.post(batch_of("gw-n1", "north", [later]), centre.north).json()["accepted"] == 1


def test_a_baseline_resent_takes_its_deactivation_and_nothing_else(centre: Centre):
    history = [node_record("gw-n1", "pipe-1"), measurement_record("gw-n1", "pipe-1", 1),
               measurement_record("gw-n1", "pipe-1", 2), baseline_record("gw-n1", "pipe-1", 1, 1)]
    assert centre.post(batch_of("gw-n1", "north", history), centre.north).status_code == 200
    off_at = T0 + timedelta(days=3)
    deactivated = baseline_record("gw-n1", "pipe-1", 1, 1, active=False, deactivated_at=off_at)
    new = baseline_record("gw-n1", "pipe-1", 2, 2, reason="after the repair")
    stored = centre.post(batch_of("gw-n1", "north", [deactivated, new]), centre.north).json()
    assert (stored["accepted"], stored["duplicates"]) == (2, 0)
    assert centre.post(batch_of("gw-n1", "north", [deactivated, new]), centre.north).json()["duplicates"] == 2
    # An older view that has it active is ignored; one that changes what it is, refused.
    assert centre.post(batch_of("gw-n1", "north", [baseline_record("gw-n1", "pipe-1", 1, 1)]),
                       centre.north).json()["stale"] == 1
    rewritten = baseline_record("gw-n1", "pipe-1", 1, 2, active=False, deactivated_at=off_at)
    body = assert_problem(centre.post(batch_of("gw-n1", "north", [rewritten]), centre.north), 422, "ingest-bad-record")
    assert "measurement_uid" in body["bad_record"]["error"]

    listed = centre.get("/nodes/pipe-1/baselines").json()
    assert [(b["reason"], b["active"]) for b in listed] == [("after the repair", True), ("commissioning", False)]
    with centre.database.session() as session:
        first = session.scalars(select(BaselineRow).order_by(BaselineRow.id)).first()
        assert first is not None and first.deactivated_at == off_at


def test_gzip_bodies_are_accepted_and_the_limit_holds_after_inflating(sqlite_url: str):
    with serve_centre(sqlite_url, ingest_max_body_bytes=200_000) as centre:
        small = batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 1))
        zipped = gzip.compress(small.model_dump_json().encode())
        assert centre.post(zipped, centre.north, **{"Content-Encoding": "gzip"}).status_code == 200
        # A small gzip body that inflates past the limit (a "bomb"): refused once inflated that far.
        raw = small.model_dump_json().encode() + b" " * 300_000
        assert len(gzip.compress(raw)) < 200_000
        refused = centre.post(gzip.compress(raw), centre.north, **{"Content-Encoding": "gzip"})
        assert "once gzip is undone" in assert_problem(refused, 413, "payload-too-large")["detail"]
        assert_problem(centre.post(raw, centre.north), 413, "payload-too-large")
        assert_problem(centre.post(zipped[:-9], centre.north, **{"Content-Encoding": "gzip"}), 415,
                       "unsupported-media-type")
        assert centre.count(MeasurementRow) == 1


def test_alert_events_get_central_deliveries_only_when_the_gateway_leaves_them_to_the_centre(centre: Centre):
    left = alert_record("gw-n1", "pipe-1", central=True)
    sent_at_edge = alert_record("gw-n1", "pipe-1", central=False)
    batch = batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1"), left, sent_at_edge])
    assert centre.post(batch, centre.north).json()["accepted"] == 3
    with centre.database.session() as session:
        origins = {e.id: e.origin for e in session.scalars(select(EventRow))}
        sinks = {(d.event_id, d.sink) for d in session.scalars(select(DeliveryRow))}
    assert origins == {left.event_id: "edge", sent_at_edge.event_id: "edge"}
    assert sinks == {(left.event_id, "webhook-central")}


def test_a_busy_worker_answers_429_with_retry_after(sqlite_url: str):
    with serve_centre(sqlite_url, ingest_concurrency=1, ingest_retry_after_s=7) as centre:
        gate = centre.server.server.config.app.state.ingest_gate
        gate.active = 1  # one batch is being stored by this worker
        busy = centre.post(batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1")]), centre.north)
        assert_problem(busy, 429, "ingest-busy")
        assert busy.headers["retry-after"] == "7"
        gate.active = 0
        assert centre.post(batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1")]), centre.north).status_code == 200


@pytest.mark.postgres
def test_the_same_batch_from_two_workers_at_once_is_stored_once(postgres_url: str):
    with serve_centre(postgres_url) as centre:
        batch = batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 20))
        answers: list[httpx.Response] = []

        def send() -> None:
            answers.append(centre.post(batch, centre.north))

        threads = [threading.Thread(target=send) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        assert sorted(a.status_code for a in answers) == [200] * 4, [a.text for a in answers]
        assert sum(a.json()["accepted"] for a in answers if a.json()["accepted"] > 1) == 41
        assert [centre.count(m) for m in (NodeRow, MeasurementRow, DetectionRow)] == [1, 20, 20]


def test_a_resent_record_the_centre_refuses_ends_its_trace_request_refused_with_why(centre: Centre):
    """Traces on demand, over HTTP: a request answered held whose re-sent record is refused (by the
    contract's own checks or by the stored measurement's) ends ``refused`` with the refusal, and
    the measurement keeps no traces but its own; asked again, the request starts over."""
    from db.api_keys import create_api_key
    from db.models import Role
    from uplink.contract import TRACE_ANSWERS_PATH, TRACE_REQUESTS_PATH

    with centre.database.write() as session:
        operator = create_api_key(session, name="operator-ana", role=Role.OPERATOR)[1]
    assert centre.post(batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 2, traces=False)),
                       centre.north).status_code == 200
    with centre.database.session() as session:
        first, second = session.scalars(select(MeasurementRow.id).order_by(MeasurementRow.id)).all()

    def gateway_answers_held() -> None:
        asked = httpx.get(f"{centre.url}{TRACE_REQUESTS_PATH}", params={"gateway_id": "gw-n1"}, timeout=10,
                          headers={"Authorization": f"Bearer {centre.north}"}).json()["items"]
        answers = [{"request_id": a["request_id"], "measurement_uid": a["measurement_uid"], "answer": "held"}
                   for a in asked]
        answered = httpx.post(f"{centre.url}{TRACE_ANSWERS_PATH}", timeout=10,
                              json={"gateway_id": "gw-n1", "site": "north", "answers": answers},
                              headers={"Authorization": f"Bearer {centre.north}"})
        assert answered.status_code == 200 and answered.json()["updated"] == len(asked) >= 1

    def ask(measurement_id: int) -> httpx.Response:
        return httpx.post(f"{centre.url}/api/v1/measurements/{measurement_id}/traces/request", timeout=10,
                          headers={"Authorization": f"Bearer {operator}"})

    def traces(measurement_id: int) -> dict:
        return centre.get(f"/measurements/{measurement_id}").json()["traces"]

    assert ask(first).status_code == 202 and ask(second).status_code == 202
    gateway_answers_held()
    assert traces(first)["status"] == traces(second)["status"] == "held"

    # 1. Other traces under the stored measurement's uid: refused by the stored checksum (422).
    other = measurement_record("gw-n1", "pipe-1", 7).model_copy(update={"uid": "gw-n1/measurement/1"})
    body = assert_problem(centre.post(batch_of("gw-n1", "north", [other]), centre.north), 422, "ingest-bad-record")
    state = traces(first)
    assert state["status"] == "refused" and state["refused_at"]
    assert state["refusal"] == f"HTTP 422 ingest-bad-record: {body['bad_record']['error']}"
    assert "a stored measurement does not change" in state["refusal"]
    # 2. Bytes that do not match their own checksum: refused by the contract before anything is read.
    damaged = measurement_record("gw-n1", "pipe-1", 2).model_dump(mode="json")
    stored = bytearray(base64.b64decode(damaged["traces"]["data"]))
    stored[100] ^= 0x01  # one bit flipped on the way: the length is right, the checksum is not
    damaged["traces"]["data"] = base64.b64encode(stored).decode()
    raw = batch_of("gw-n1", "north", [node_record("gw-n1", "pipe-1")]).model_dump(mode="json")
    raw["records"].append(damaged)
    assert_problem(centre.post(json.dumps(raw).encode(), centre.north), 422, "ingest-bad-record")
    state = traces(second)
    assert (state["status"], state["refusal"]) == ("refused", "HTTP 422 ingest-bad-record: traces: data does not "
                                                              "match its sha256")
    with centre.database.session() as session:  # no traces taken from either
        assert all(row.traces_blob is None for row in session.scalars(select(MeasurementRow)))

    # Asked again, the request starts over; the measurement's own traces end it received.
    again = ask(first)
    assert again.status_code == 202 and again.json()["status"] == "requested" and again.json()["refusal"] is None
    gateway_answers_held()
    right = measurement_record("gw-n1", "pipe-1", 1)
    assert centre.post(batch_of("gw-n1", "north", [right]), centre.north).json()["accepted"] == 1
    assert (traces(first)["status"], traces(first)["refusal"]) == ("received", None)
    assert traces(second)["status"] == "refused"  # the other one's refusal stands until it is asked again


def test_a_refusal_that_cannot_be_noted_is_answered_503_so_the_gateway_sends_it_again(
    centre: Centre, monkeypatch: pytest.MonkeyPatch,
):
    """A trace request must not stay held because the centre could not write its refusal: the
    batch is answered 503 storage-unavailable (retried by the gateway, no refusal counted), and
    the refusal noted once the database writes again."""
    from db.errors import StorageBusy
    from db.models import TraceRequestRow
    from db.trace_requests import answer_requests, request_traces_of, traces_state
    from service import ingest as service_ingest

    assert centre.post(batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 1, traces=False)),
                       centre.north).status_code == 200
    with centre.database.write() as session:
        row = session.scalars(select(MeasurementRow)).one()
        request_traces_of(session, row, who="operator-ana")
        [request_id] = session.scalars(select(TraceRequestRow.id)).all()
        answer_requests(session, [(request_id, "gw-n1/measurement/1", "held")], site="north", gateway_id="gw-n1")

    def status() -> str:
        with centre.database.session() as session:
            return traces_state(session, session.scalars(select(MeasurementRow)).one()).status
    other = batch_of("gw-n1", "north", [measurement_record("gw-n1", "pipe-1", 7).model_copy(
        update={"uid": "gw-n1/measurement/1"})])

    def busy(*args: object, **kwargs: object) -> bool:
        raise StorageBusy("database is locked")

    monkeypatch.setattr(service_ingest, "refuse_resent", busy)
    assert_problem(centre.post(other, centre.north), 503, "storage-unavailable")
    assert status() == "held"
    monkeypatch.undo()
    assert_problem(centre.post(other, centre.north), 422, "ingest-bad-record")
    assert status() == "refused"

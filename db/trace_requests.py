"""Raw traces on demand, the central site's side: an operator's requests for the traces of measurements
a gateway sent without them (revision 0009, docs/gateway.md "Uplink").

A request is recorded here (``requested``); the gateway, which only talks outbound, polls for the
``requested`` ones of its site (:func:`pending_requests`) and answers each ``held`` (it queued the
measurement again with its traces) or ``pruned`` (it no longer holds them) (:func:`answer_requests`);
the ingest of the measurement with its traces makes it ``received`` (:func:`mark_received`), and a
refusal of the record the gateway re-sent makes it ``refused``, with the refusal (:func:`refuse_resent`,
revision 0012): the request ends there instead of waiting for traces that will not come.
One request per measurement: asking again (after the centre's own retention dropped traces it had
received, or after a refusal) reuses the row. What a measurement's traces are, for the API, is :func:`traces_status` (pure).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Literal, cast

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import StorageError
from db.models import IngestedRecordRow, MeasurementRow, NodeRow, TraceRequestRow, TraceRequestStatus

TracesStatus = Literal["stored", "received", "requested", "held", "pruned", "refused", "at_gateway", "pruned_here"]
RequestOutcome = Literal["here", "gone", "pending", "asked"]
MAX_REFUSAL_CHARS = 2000  # what is kept of a refusal's text


class TraceAnswerRefused(StorageError):
    """A gateway's answer names a request that is not one of its own (``index``: which answer)."""

    def __init__(self, index: int, error: str) -> None:
        super().__init__(f"answer {index}: {error}")
        self.index = index
        self.error = error


def traces_status(*, here: bool, from_gateway: bool, request: TraceRequestStatus | None) -> TracesStatus:
    """Where a measurement's raw traces are (pure).

    ``stored`` / ``received``: here (``received``: after a request). ``requested``: asked, the
    gateway has not answered; ``held``: the gateway holds them and queued them; ``pruned``: the
    gateway answered it no longer holds them; ``refused``: the gateway re-sent the measurement and
    this site refused the record. ``at_gateway``: a gateway's measurement sent without
    them and not asked for (they can be requested); ``pruned_here``: this site's own retention
    removed them and no gateway has them to send.
    """
    if here:
        return "received" if request == TraceRequestStatus.RECEIVED else "stored"
    if request is not None and request != TraceRequestStatus.RECEIVED:
        return cast(TracesStatus, request.value)  # requested, held, pruned, refused
    return "at_gateway" if from_gateway else "pruned_here"


def request_outcome(status: TracesStatus) -> RequestOutcome:
    """What asking for the traces of a measurement in ``status`` does (pure): ``here`` (nothing to
    ask), ``gone`` (no one holds them), ``pending`` (asked already, the answer stands), ``asked``.

    ``refused`` asks again: the gateway still holds the traces (its retention keeps those of a record
    the centre refused), and the cause may have been put right at either end since; the same
    record is refused the same way, and says so again."""
    if status in ("stored", "received"):
        return "here"
    if status in ("pruned", "pruned_here"):
        return "gone"
    if status in ("requested", "held"):
        return "pending"
    return "asked"


@dataclass(frozen=True)
class TracesState:
    """A measurement's traces as the API shows them: the status and, if they were asked for, the request."""

    status: TracesStatus
    gateway_id: str | None = None  # the gateway that sent the measurement (None: this site's own)
    measurement_uid: str | None = None
    requested_by: str | None = None
    requested_at: datetime | None = None
    answered_at: datetime | None = None
    received_at: datetime | None = None
    refused_at: datetime | None = None
    refusal: str | None = None  # why this site refused the record the gateway re-sent (status refused)


def edge_record(session: Session, measurement_id: int) -> IngestedRecordRow | None:
    """The ingest record of a measurement held here (its gateway and edge uid); None: this site's own."""
    return session.scalars(
        select(IngestedRecordRow)
        .where(IngestedRecordRow.kind == "measurement", IngestedRecordRow.central_id == str(measurement_id))
        .limit(1)
    ).first()


def _request(session: Session, measurement_id: int) -> TraceRequestRow | None:
    return session.scalars(select(TraceRequestRow).where(TraceRequestRow.measurement_id == measurement_id)).first()


def _state(measurement: MeasurementRow, edge: IngestedRecordRow | None, request: TraceRequestRow | None) -> TracesState:
    status = traces_status(here=measurement.traces_pruned_at is None, from_gateway=edge is not None,
                           request=None if request is None else request.status)
    if request is None:
        return TracesState(status, gateway_id=None if edge is None else edge.gateway_id,
                           measurement_uid=None if edge is None else edge.uid)
    return TracesState(status, gateway_id=request.gateway_id, measurement_uid=request.measurement_uid,
                       requested_by=request.requested_by, requested_at=request.requested_at,
                       answered_at=request.answered_at, received_at=request.received_at,
                       refused_at=request.refused_at, refusal=request.refusal)


def traces_state(session: Session, measurement: MeasurementRow) -> TracesState:
    return _state(measurement, edge_record(session, measurement.id), _request(session, measurement.id))


def request_traces_of(
    session: Session, measurement: MeasurementRow, *, who: str, now: datetime | None = None,
) -> tuple[RequestOutcome, TracesState]:
    """Ask the measurement's gateway for its traces (call inside ``Database.write()``); the outcome
    and the traces' state after it. Only ``asked`` writes: a request pending already is left as it is."""
    edge = edge_record(session, measurement.id)
    request = _request(session, measurement.id)
    outcome = request_outcome(_state(measurement, edge, request).status)
    if outcome != "asked":
        return outcome, _state(measurement, edge, request)
    assert edge is not None  # at_gateway: the measurement came from a gateway
    node = session.get(NodeRow, measurement.node_id)
    site = node.site if node is not None and node.site is not None else ""
    if request is None:
        request = TraceRequestRow(measurement_id=measurement.id, measurement_uid=edge.uid, gateway_id=edge.gateway_id,
                                  site=site)
        session.add(request)
    request.status = TraceRequestStatus.REQUESTED
    request.requested_by = who
    request.requested_at = now or utc_now()
    request.answered_at = request.received_at = request.refused_at = None
    request.refusal = None
    session.flush()
    return outcome, _state(measurement, edge, request)


def pending_requests(session: Session, *, site: str, gateway_id: str, limit: int) -> list[TraceRequestRow]:
    """The gateway's requests it has not answered, oldest first."""
    return list(session.scalars(
        select(TraceRequestRow)
        .where(TraceRequestRow.site == site, TraceRequestRow.gateway_id == gateway_id,
               TraceRequestRow.status == TraceRequestStatus.REQUESTED)
        .order_by(TraceRequestRow.id)
        .limit(limit)
    ))


Answer = tuple[int, str, Literal["held", "pruned"]]  # request id, measurement uid, answer


def answer_requests(
    session: Session, answers: Sequence[Answer], *, site: str, gateway_id: str, now: datetime | None = None,
) -> int:
    """Apply a gateway's answers (inside ``Database.write()``); returns how many moved a request on.

    Only a ``requested`` request takes an answer: a repeated one, or one arriving after the traces
    did (``received``), changes nothing. An answer naming another gateway's request, or the wrong
    measurement, raises :class:`TraceAnswerRefused` (the caller rolls the whole back).
    """
    updated = 0
    for index, (request_id, uid, answer) in enumerate(answers):
        request = session.get(TraceRequestRow, request_id)
        if request is None or (request.site, request.gateway_id) != (site, gateway_id):
            raise TraceAnswerRefused(index, f"request {request_id} is not one of gateway {gateway_id!r}'s")
        if request.measurement_uid != uid:
            raise TraceAnswerRefused(index, f"request {request_id} is for {request.measurement_uid!r}, not {uid!r}")
        if request.status == TraceRequestStatus.REQUESTED:
            request.status = TraceRequestStatus(answer)
            request.answered_at = now or utc_now()
            updated += 1
    session.flush()
    return updated


def mark_received(session: Session, measurement_id: int, *, now: datetime | None = None) -> None:
    """The measurement's traces arrived: its request (if any) is ``received``."""
    request = _request(session, measurement_id)
    if request is not None and request.status != TraceRequestStatus.RECEIVED:
        request.status = TraceRequestStatus.RECEIVED
        request.received_at = now or utc_now()
        request.refused_at, request.refusal = None, None


_AWAITING = (TraceRequestStatus.REQUESTED, TraceRequestStatus.HELD)


def refuse_resent(
    session: Session, measurement_uid: str, refusal: str, *, site: str, now: datetime | None = None,
) -> bool:
    """This site refused a gateway's record of ``measurement_uid`` (call inside ``Database.write()``,
    after the batch's own transaction rolled back): a request of ``site`` for its traces still
    awaiting them (``requested`` or ``held``) is ``refused``, with ``refusal``; True if one was.

    Anything else is left as it is: no request, one of another site (a key writes for its own
    site only), one ``received`` (the traces are here: a record that disagrees with them changes
    nothing), ``pruned``, or ``refused`` already (a gateway tries a refused record again a few
    times: the first refusal stands, like a first answer).
    """
    edge = session.get(IngestedRecordRow, measurement_uid)
    if edge is None or edge.kind != "measurement":
        return False  # not a measurement held here: no request can be waiting for it
    request = _request(session, int(edge.central_id))
    if request is None or request.site != site or request.status not in _AWAITING:
        return False
    request.status = TraceRequestStatus.REFUSED
    request.refused_at = now or utc_now()
    request.refusal = refusal[:MAX_REFUSAL_CHARS]
    session.flush()
    return True

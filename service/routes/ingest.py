"""``POST /ingest/batches``: a gateway's records, stored whole or refused whole; ``/ingest/trace-requests``:
the operators' requests for raw traces the gateway did not send, and its answers (gateway keys only)."""
from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from db.database import Database
from db.ingest import IngestRefused
from db.trace_requests import TraceAnswerRefused, answer_requests, pending_requests
from service import ingest
from service.deps import DatabaseDep, GatewayCaller
from service.problems import (
    CONFLICT,
    FORBIDDEN,
    PAYLOAD_TOO_LARGE,
    UNSUPPORTED_MEDIA_TYPE,
    ApiProblem,
    ProblemKind,
    problem_response,
    problem_responses,
)
from uplink.contract import (
    MAX_TRACE_REQUESTS,
    PROBLEM_BAD_RECORD,
    BadRecord,
    GatewayId,
    IngestBatch,
    IngestResult,
    TraceAnswers,
    TraceAnswersResult,
    TraceRequest,
    TraceRequests,
)

router = APIRouter(prefix="/ingest", tags=["ingest"], responses=problem_responses(401, 403, 503))

BAD_RECORD = ProblemKind(PROBLEM_BAD_RECORD.rsplit(":", 1)[1], 422, "The batch was refused: one of its records is bad")
UNKNOWN_REFERENCE = ProblemKind("ingest-unknown-reference", 409, "The batch refers to a record not held here")
BUSY = ProblemKind("ingest-busy", 429, "The centre is storing as many batches as it takes; retry later")
_REFUSALS = {"invalid": BAD_RECORD, "forbidden": FORBIDDEN, "unknown-reference": UNKNOWN_REFERENCE}

_BODY_SCHEMA = {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/IngestBatch"}}},
                "required": True,
                "description": "uplink/contract.py's IngestBatch; `Content-Encoding: gzip` accepted"}


async def _refused(kind: ProblemKind, bad: BadRecord, request: Request, database: Database, site: str) -> JSONResponse:
    """The refusal of a batch; a trace request awaiting the refused record's traces ends ``refused`` first."""
    await run_in_threadpool(ingest.note_refusal, database, bad.kind, bad.uid,
                            f"HTTP {kind.status} {kind.slug}: {bad.error}", key_site=site)
    detail = bad.error if bad.index is None else f"record {bad.index} ({bad.uid}): {bad.error}"
    return problem_response(kind, detail, request, extra={"bad_record": bad.model_dump()})


@router.post(
    "/batches",
    summary="Store a gateway's batch of records, whole or not at all (gateway key of the batch's site)",
    response_model=IngestResult,
    openapi_extra={"requestBody": _BODY_SCHEMA},
    responses=problem_responses(409, 413, 415, 422, 429),
)
async def ingest_batch(request: Request, caller: GatewayCaller, database: DatabaseDep) -> Any:
    settings = request.app.state.settings
    gate: ingest.IngestGate = request.app.state.ingest_gate
    if not gate.try_enter():
        return problem_response(BUSY, f"{gate.limit} batches are being stored by this worker", request,
                                headers={"Retry-After": str(settings.ingest_retry_after_s)})
    try:
        body = await request.body()
        try:
            raw = ingest.undo_content_encoding(body, request.headers.get("content-encoding"),
                                               max_bytes=settings.ingest_max_body_bytes)
        except ingest.BodyTooLarge as exc:
            return problem_response(PAYLOAD_TOO_LARGE, str(exc), request)
        except ingest.BodyUnreadable as exc:
            return problem_response(UNSUPPORTED_MEDIA_TYPE, str(exc), request)
        try:
            batch = await run_in_threadpool(ingest.parse_batch, raw)
        except ValidationError as exc:
            return await _refused(BAD_RECORD, BadRecord(**ingest.bad_record_of(exc, raw)), request, database,
                                  caller.site or "")
        try:
            outcome = await run_in_threadpool(ingest.store, database, batch, key_site=caller.site or "",
                                              alert_sinks=list(settings.central_alert_sinks))
        except IngestRefused as exc:
            bad = BadRecord(index=exc.index, uid=exc.uid, kind=exc.kind, error=exc.error)
            return await _refused(_REFUSALS[exc.reason], bad, request, database, caller.site or "")
        return IngestResult(batch_id=batch.batch_id, accepted=outcome.accepted, duplicates=outcome.duplicates,
                            stale=outcome.stale)
    finally:
        gate.leave()


@router.get("/trace-requests", summary="The trace requests this gateway has not answered, oldest first (gateway key)")
def list_trace_requests(
    caller: GatewayCaller, database: DatabaseDep,
    gateway_id: Annotated[GatewayId, Query(description="the polling gateway's id (its records' uid prefix)")],
) -> TraceRequests:
    with database.session() as session:
        rows = pending_requests(session, site=caller.site or "", gateway_id=gateway_id, limit=MAX_TRACE_REQUESTS)
        items = [TraceRequest(request_id=r.id, measurement_uid=r.measurement_uid, requested_at=r.requested_at)
                 for r in rows]
    return TraceRequests(gateway_id=gateway_id, items=items)


@router.post("/trace-requests/answers", responses=problem_responses(409, 422),
             summary="A gateway's answers to trace requests: held (queued for upload) or pruned (gateway key)")
def answer_trace_requests(body: TraceAnswers, caller: GatewayCaller, database: DatabaseDep) -> TraceAnswersResult:
    if body.site != caller.site:
        raise ApiProblem(FORBIDDEN, f"this key answers for site {caller.site!r}, the answers are for site {body.site!r}")
    answers = [(a.request_id, a.measurement_uid, a.answer) for a in body.answers]
    try:
        with database.write() as session:
            updated = answer_requests(session, answers, site=body.site, gateway_id=body.gateway_id)
    except TraceAnswerRefused as exc:
        raise ApiProblem(CONFLICT, str(exc)) from None
    return TraceAnswersResult(updated=updated)


def batch_schema_components() -> dict[str, Any]:
    """The IngestBatch schema and its parts, for the OpenAPI document's components."""
    schema = IngestBatch.model_json_schema(ref_template="#/components/schemas/{model}")
    components: dict[str, Any] = schema.pop("$defs", {})
    components["IngestBatch"] = schema
    return components

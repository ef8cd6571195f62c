"""Errors as RFC 9457 problem details (``application/problem+json``), one stable type URI each.

Every error leaves the server through :func:`problem_response`: typed storage errors map to
their status here, validation errors become 422, and anything unexpected becomes a 500
problem that is logged with its traceback server-side and shows no internals to the client.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from db.errors import (
    BaselineError,
    CorruptBlob,
    DatabaseDamaged,
    ForeignDatabase,
    InvalidCursor,
    NotFound,
    SchemaOutOfDate,
    StateConflict,
    StorageError,
    StorageUnavailable,
    TracesPruned,
)

log = logging.getLogger("pipesentry.api")

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:pipesentry:problem:"


class Problem(BaseModel):
    """RFC 9457 problem details."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(description="stable URI naming the kind of error, e.g. urn:pipesentry:problem:not-found")
    title: str = Field(description="short summary of the kind of error")
    status: int = Field(description="the HTTP status code")
    detail: str | None = Field(None, description="what went wrong in this request")
    instance: str | None = Field(None, description="the request path")


class FieldError(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ValidationProblem(Problem):
    errors: list[FieldError] = Field(default_factory=list, description="one entry per invalid field")


@dataclass(frozen=True)
class ProblemKind:
    slug: str
    status: int
    title: str

    @property
    def type_uri(self) -> str:
        return TYPE_PREFIX + self.slug


UNAUTHORIZED = ProblemKind("unauthorized", 401, "Missing or invalid API key")
FORBIDDEN = ProblemKind("forbidden", 403, "The API key's role does not allow this")
NOT_FOUND = ProblemKind("not-found", 404, "Not found")
METHOD_NOT_ALLOWED = ProblemKind("method-not-allowed", 405, "Method not allowed")
NOT_ACCEPTABLE = ProblemKind("not-acceptable", 406, "Not acceptable")
CONFLICT = ProblemKind("conflict", 409, "Conflicts with the current state")
TRACES_PRUNED = ProblemKind("traces-pruned", 410, "Raw traces were removed by retention")
PAYLOAD_TOO_LARGE = ProblemKind("payload-too-large", 413, "Request body too large")
UNSUPPORTED_MEDIA_TYPE = ProblemKind("unsupported-media-type", 415, "Unsupported media type")
VALIDATION = ProblemKind("validation-error", 422, "The request is invalid")
INVALID_CURSOR = ProblemKind("invalid-cursor", 400, "Malformed pagination cursor")
BAD_REQUEST = ProblemKind("bad-request", 400, "Bad request")
BASELINE_REFUSED = ProblemKind("baseline-refused", 409, "This measurement cannot be the node's baseline")
STORAGE_UNAVAILABLE = ProblemKind("storage-unavailable", 503, "The database is unavailable; retry later")
SERVER_BUSY = ProblemKind("server-busy", 503, "Too many requests in progress; retry shortly")
SCHEMA_OUT_OF_DATE = ProblemKind("schema-out-of-date", 503, "The database schema does not match this release")
DATABASE_DAMAGED = ProblemKind("database-damaged", 503, "The database file is damaged; it must be restored")
FOREIGN_DATABASE = ProblemKind("foreign-database", 503, "The database file is not PipeSentry's")
CORRUPT_DATA = ProblemKind("corrupt-data", 500, "Stored data failed its integrity check")
INTERNAL = ProblemKind("internal-error", 500, "Internal error (logged on the server)")

_BY_STATUS = {
    kind.status: kind
    for kind in (UNAUTHORIZED, FORBIDDEN, NOT_FOUND, METHOD_NOT_ALLOWED, NOT_ACCEPTABLE, PAYLOAD_TOO_LARGE,
                 UNSUPPORTED_MEDIA_TYPE, VALIDATION, BAD_REQUEST, INTERNAL)
}

# Most specific first: the first isinstance match wins.
_STORAGE_KINDS: tuple[tuple[type[StorageError], ProblemKind], ...] = (
    (NotFound, NOT_FOUND),
    (TracesPruned, TRACES_PRUNED),
    (InvalidCursor, INVALID_CURSOR),
    (BaselineError, BASELINE_REFUSED),
    (StateConflict, CONFLICT),
    (SchemaOutOfDate, SCHEMA_OUT_OF_DATE),
    (DatabaseDamaged, DATABASE_DAMAGED),
    (ForeignDatabase, FOREIGN_DATABASE),
    (StorageUnavailable, STORAGE_UNAVAILABLE),
    (CorruptBlob, CORRUPT_DATA),
)


class ApiProblem(StarletteHTTPException):
    """Raise anywhere in a request to answer with a problem of ``kind``.

    A Starlette ``HTTPException`` so that FastAPI passes it through unchanged even when it
    is raised while the request body is being read (the size limit does that).
    """

    def __init__(self, kind: ProblemKind, detail: str | None = None, headers: dict[str, str] | None = None) -> None:
        super().__init__(kind.status, detail=detail or kind.title, headers=headers)
        self.kind = kind


def problem_response(
    kind: ProblemKind,
    detail: str | None,
    request: Request | None,
    *,
    headers: dict[str, str] | None = None,
    extra: dict[str, Any] | None = None,
) -> JSONResponse:
    body = Problem(
        type=kind.type_uri,
        title=kind.title,
        status=kind.status,
        detail=detail,
        instance=None if request is None else request.url.path,
    ).model_dump(exclude_none=True)
    body.update(extra or {})
    return JSONResponse(jsonable_encoder(body), status_code=kind.status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def storage_problem(error: StorageError) -> ProblemKind:
    for error_type, kind in _STORAGE_KINDS:
        if isinstance(error, error_type):
            return kind
    return INTERNAL


# FastAPI's answer to a body it cannot decode (not UTF-8, say): said in our words instead.
_FASTAPI_BODY_ERROR = "There was an error parsing the body"
BODY_NOT_JSON = "the request body is not JSON in UTF-8"


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app answers on this request's path (for a 405's ``Allow``).

    Starlette names only the methods of the first route that matched the path; a path served
    by several routes (``GET`` and ``PATCH /nodes/{id}``) has them all. Asked of the router
    itself, method by method, so that included routers are searched as they are for a request.
    """
    routes = request.app.router.routes
    return [method for method in _METHODS
            if any(route.matches({**request.scope, "method": method})[0] == Match.FULL for route in routes)]


async def _on_http_exception(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    kind = exc.kind if isinstance(exc, ApiProblem) else _BY_STATUS.get(exc.status_code)
    if kind is None:
        kind = ProblemKind(f"http-{exc.status_code}", exc.status_code, str(exc.detail))
    detail = exc.detail if isinstance(exc.detail, str) else kind.title
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 400 and detail == _FASTAPI_BODY_ERROR:
        detail = BODY_NOT_JSON
    if exc.status_code == 405:
        headers["Allow"] = ", ".join(allowed_methods(request)) or headers.get("Allow", "")
    return problem_response(kind, detail, request, headers=headers or None)


async def _on_validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    # Only location, message and type: the rejected input is not echoed back.
    errors = [
        FieldError(loc=[part if isinstance(part, int) else str(part) for part in err.get("loc", ())],
                   msg=str(err.get("msg", "")), type=str(err.get("type", ""))).model_dump()
        for err in exc.errors()
    ]
    where = ", ".join(".".join(str(p) for p in e["loc"]) for e in errors[:5])
    return problem_response(VALIDATION, f"invalid: {where}" if where else VALIDATION.title, request,
                            extra={"errors": errors})


async def _on_storage_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StorageError)
    kind = storage_problem(exc)
    if kind.status >= 500:
        log.error("%s %s: %s: %s", request.method, request.url.path, type(exc).__name__, exc)
    headers = {"Retry-After": "5"} if kind.status == 503 else None
    # A 503 names why in one word too (storage_unavailable, database_damaged, ...): what a probe or a script reads.
    extra = {"reason": kind.slug.replace("-", "_")} if kind.status == 503 else None
    return problem_response(kind, str(exc) if kind.status < 500 or kind.status == 503 else kind.title, request,
                            headers=headers, extra=extra)


async def _on_unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error in %s %s", request.method, request.url.path, exc_info=exc)
    return problem_response(INTERNAL, INTERNAL.title, request)


def install_problem_handlers(app: FastAPI) -> None:
    app.add_exception_handler(StarletteHTTPException, _on_http_exception)
    app.add_exception_handler(RequestValidationError, _on_validation_error)
    app.add_exception_handler(StorageError, _on_storage_error)
    app.add_exception_handler(Exception, _on_unexpected)


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries documenting the problems a route can answer."""
    described = {
        400: "Malformed request (e.g. a bad cursor)",
        401: UNAUTHORIZED.title,
        403: FORBIDDEN.title,
        404: NOT_FOUND.title,
        409: CONFLICT.title,
        410: TRACES_PRUNED.title,
        413: PAYLOAD_TOO_LARGE.title,
        503: STORAGE_UNAVAILABLE.title,
    }
    out: dict[int | str, dict[str, Any]] = {}
    for status in statuses:
        out[status] = {
            "description": described.get(status, "Problem"),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
    return out

"""Liveness, readiness and Prometheus metrics."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response

from service import schemas
from service.database import DatabaseGate
from service.deps import require_viewer
from service.metrics import exposition
from service.problems import problem_responses
from service.settings import ApiSettings

PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"


def health_router(settings: ApiSettings) -> APIRouter:
    router = APIRouter(tags=["health"])

    @router.get("/healthz", summary="Liveness: the process answers (no key needed)")
    def healthz() -> schemas.Liveness:
        return schemas.Liveness()

    @router.get("/readyz", responses=problem_responses(503),
                summary="Readiness: database reachable and its schema at this release's revision (no key needed)")
    def readyz(request: Request) -> schemas.Readiness:
        gate: DatabaseGate = request.app.state.database
        return schemas.Readiness(schema_revision=gate.check_ready())

    metrics_guard = [Depends(require_viewer)] if settings.metrics_require_key else []

    @router.get(
        "/metrics",
        response_class=Response,
        dependencies=metrics_guard,
        responses={
            200: {"description": "Prometheus text format", "content": {PROMETHEUS_TEXT: {"schema": {"type": "string"}}}},
            **problem_responses(*([401, 403] if settings.metrics_require_key else [])),
        },
        summary="Prometheus metrics per node (needs a key unless metrics_require_key=false)",
    )
    def metrics(request: Request) -> Response:
        return Response(exposition(request.app.state.metrics), media_type=PROMETHEUS_TEXT)

    return router

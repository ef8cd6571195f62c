"""The API application: ``create_app(settings)`` wires routes, problems, limits, CORS and metrics."""
from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service import problems
from service.database import DatabaseGate
from service.deps import VerifiedKeys
from service.head import HeadAsGet
from service.ingest import IngestGate
from service.limits import BodySizeLimit, RequestsInFlightLimit
from service.maps import HeatmapRenderer
from service.metrics import metrics_registry
from service.routes import alerts, detections, fleet, ingest, keys, measurements, nodes
from service.routes.api_docs import install_api_docs
from service.routes.dashboard import STATIC_DIR, dashboard_router
from service.routes.health import health_router
from service.settings import ApiSettings

log = logging.getLogger("pipesentry.api")

API_VERSION = "1"
DESCRIPTION = """Operator API of PipeSentry: nodes, measurements, raw traces, DI maps,
baselines, detections and alerts. Every request except `/healthz`, `/readyz` and the
dashboard shell needs an API key (`Authorization: Bearer <key>` or `X-API-Key: <key>`);
roles are viewer (read), operator (also baselines and alerts), admin (also keys). Errors are
RFC 9457 problem details (`application/problem+json`). See docs/api.md."""


class SecurityHeaders:
    """nosniff everywhere; API answers carry keys' data, so they are not stored by caches."""

    def __init__(self, app: ASGIApp, api_prefix: str) -> None:
        self.app = app
        self.api_prefix = api_prefix.encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        is_api = scope.get("raw_path", scope["path"].encode()).startswith(self.api_prefix)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                names = {name.lower() for name, _ in headers}
                headers.append((b"x-content-type-options", b"nosniff"))
                if is_api and b"cache-control" not in names:
                    headers.append((b"cache-control", b"no-store"))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def create_app(settings: ApiSettings | None = None) -> FastAPI:
    settings = settings or ApiSettings()
    gate = DatabaseGate(settings.database_url, busy_timeout_ms=settings.busy_timeout_ms,
                        integrity_check_every_s=settings.integrity_check_every_s,
                        min_free_bytes=settings.min_free_bytes)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        try:
            yield
        finally:
            gate.dispose()

    app = FastAPI(
        title="PipeSentry operator API",
        version=API_VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
        openapi_url=f"{settings.base_path}/openapi.json",
        docs_url=None,  # served below from local files, not a CDN
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.database = gate
    app.state.heatmaps = HeatmapRenderer()
    app.state.verified_keys = VerifiedKeys(settings.key_cache_ttl_s)
    app.state.metrics = metrics_registry(gate)
    app.state.ingest_gate = IngestGate(settings.ingest_concurrency)

    problems.install_problem_handlers(app)
    for router in (nodes.router, fleet.router, measurements.router, detections.router, alerts.router, keys.router,
                   ingest.router):
        app.include_router(router, prefix=settings.base_path)
    app.include_router(health_router(settings))
    app.include_router(dashboard_router(settings))
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    install_api_docs(app, docs_url=f"{settings.base_path}/docs", openapi_url=f"{settings.base_path}/openapi.json",
                     title=app.title)

    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "PATCH", "DELETE"],
            allow_headers=["Authorization", "X-API-Key", "Content-Type"],
            max_age=600,
        )
    app.add_middleware(HeadAsGet)
    app.add_middleware(SecurityHeaders, api_prefix=settings.base_path)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes,
                       larger={f"{settings.base_path}/ingest/batches": settings.ingest_max_body_bytes})
    app.add_middleware(RequestsInFlightLimit, max_requests=settings.max_requests_in_flight)  # outermost
    app.openapi = lambda: _openapi_with_problems(app)  # type: ignore[method-assign]
    return app


def _openapi_with_problems(app: FastAPI) -> dict[str, Any]:
    """FastAPI's schema, with problem+json bodies for every error and 422 described as one."""
    if app.openapi_schema is not None:
        return app.openapi_schema
    from fastapi.openapi.utils import get_openapi

    schema = get_openapi(
        title=app.title, version=app.version, description=app.description, routes=app.routes, tags=app.openapi_tags
    )
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in (problems.Problem, problems.ValidationProblem):
        definition = model.model_json_schema(ref_template="#/components/schemas/{model}")
        components.update(definition.pop("$defs", {}))
        components[model.__name__] = definition
    components.update(ingest.batch_schema_components())
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    validation = {
        "description": problems.VALIDATION.title,
        "content": {problems.PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/ValidationProblem"}}},
    }
    for path_item in schema.get("paths", {}).values():
        for operation in path_item.values():
            responses = operation.get("responses", {})
            if "422" in responses:
                responses["422"] = validation
    app.openapi_schema = schema
    return schema


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory service.app:app_from_env`` (settings from PIPESENTRY_API_*)."""
    return create_app(ApiSettings())

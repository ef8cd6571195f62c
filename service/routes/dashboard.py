"""The dashboard's static shell at ``/`` (no key: it holds no data; its script calls the API with one)."""
from __future__ import annotations

import html
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

from service.settings import ApiSettings

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
# Scripts and images from this origin only; PNGs arrive as blob: URLs fetched with the key.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; script-src 'self'; "
    "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
)


def dashboard_router(settings: ApiSettings) -> APIRouter:
    router = APIRouter(include_in_schema=False)
    page = (
        (STATIC_DIR / "index.html")
        .read_text(encoding="utf-8")
        .replace("{{API_BASE}}", html.escape(settings.base_path))
        .replace("{{REFRESH_S}}", html.escape(f"{settings.dashboard_refresh_s:g}"))
    )

    @router.get("/", response_class=HTMLResponse)
    def dashboard() -> HTMLResponse:
        return HTMLResponse(page, headers={"Content-Security-Policy": CONTENT_SECURITY_POLICY,
                                           "Cache-Control": "no-cache"})

    return router

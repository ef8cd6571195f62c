"""Swagger UI at ``{base_path}/docs``, its assets served from the installed swagger-ui-bundle-v2 package.

FastAPI's default page loads them from a CDN: on an edge computer without internet it is blank.
This is FastAPI's documented self-hosting (docs_url=None, the page from ``get_swagger_ui_html``
pointing at local files), with the files from a pinned package instead of copies in the repository.
"""
from __future__ import annotations

import swagger_ui_bundle
from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

# Outside the API prefix: API answers are marked no-store; these files may be cached (they carry ETags).
ASSETS_PATH = "/swagger-ui"


def install_api_docs(app: FastAPI, *, docs_url: str, openapi_url: str, title: str) -> None:
    app.mount(ASSETS_PATH, StaticFiles(directory=str(swagger_ui_bundle.swagger_ui_path)), name="swagger-ui")

    @app.get(docs_url, include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{title} — Swagger UI",
            swagger_js_url=f"{ASSETS_PATH}/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS_PATH}/swagger-ui.css",
            swagger_favicon_url=f"{ASSETS_PATH}/favicon-32x32.png",
        )

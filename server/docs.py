"""``/docs`` without the internet: FastAPI's Swagger UI page loads its JavaScript and CSS from a CDN, so
offline (a field laptop, an air-gapped lab) it is a blank page. Here the page is FastAPI's own, with the
assets served under ``/docs-assets`` from the ``swagger-ui-bundle-v2`` package: Swagger UI 5, since
FastAPI writes OpenAPI 3.1, which Swagger UI 4 cannot render."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

ASSETS = "/docs-assets"


def swagger_ui_dir() -> Path:
    """The folder of the packaged Swagger UI distribution (swagger-ui-bundle.js, swagger-ui.css, ...)."""
    import swagger_ui_bundle

    return Path(swagger_ui_bundle.swagger_ui_path)


def install_offline_docs(app: FastAPI) -> None:
    """Serve ``/docs`` from local assets; the app must be built with ``docs_url=None``."""
    app.mount(ASSETS, StaticFiles(directory=swagger_ui_dir()), name="docs-assets")
    title = f"{app.title} - API"

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=title,
            swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{ASSETS}/favicon-32x32.png",
        )

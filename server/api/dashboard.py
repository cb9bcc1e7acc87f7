"""The web pages the app serves itself, with nothing from a CDN: the dashboard at ``/``
(``server/static/``) and the API docs at ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc),
whose scripts and styles come from the fastapi-offline package.

The dashboard is plain HTML, CSS and JavaScript with its own SVG map (no map library):
a site's frame is flat metres, which an SVG ``viewBox`` is already, so a tile map library
would add weight and a geographic projection to undo, and nothing to vendor or license.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from server.api.deps import Device
from server.auth import Scope

STATIC = Path(__file__).resolve().parent.parent / "static"
DOCS_ASSETS = Path(fastapi_offline.__file__).resolve().parent / "static"

router = APIRouter(include_in_schema=False)
api = APIRouter(prefix="/api/v1", tags=["service"])


class WhoAmI(BaseModel):
    scope: Scope = Field(description="`admin` or `device`: what the key may do.")


@api.get("/whoami", response_model=WhoAmI)
async def whoami(principal: Device) -> WhoAmI:
    """The scope of the caller's key (extension; the dashboard asks it once): any valid key
    gets `200`, so a client learns its scope without provoking a `403`."""
    return WhoAmI(scope=principal.scope)


@router.get("/")
async def dashboard() -> FileResponse:
    return FileResponse(STATIC / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})


@router.get("/docs")
async def swagger_ui(request: Request) -> HTMLResponse:
    root = request.scope.get("root_path", "")
    return get_swagger_ui_html(
        openapi_url=f"{root}{request.app.openapi_url}",
        title=f"{request.app.title} - Swagger UI",
        oauth2_redirect_url=f"{root}/docs/oauth2-redirect",
        swagger_js_url=f"{root}/static/docs/swagger-ui-bundle.js",
        swagger_css_url=f"{root}/static/docs/swagger-ui.css",
        swagger_favicon_url=f"{root}/static/docs/favicon.png",
    )


@router.get("/docs/oauth2-redirect")
async def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc")
async def redoc(request: Request) -> HTMLResponse:
    root = request.scope.get("root_path", "")
    page = get_redoc_html(
        openapi_url=f"{root}{request.app.openapi_url}",
        title=f"{request.app.title} - ReDoc",
        redoc_js_url=f"{root}/static/docs/redoc.standalone.js",
        redoc_favicon_url=f"{root}/static/docs/favicon.png",
        with_google_fonts=False,
    )
    # ReDoc's bundle links its "powered by" logo from its CDN: images stay on this server
    page.headers["Content-Security-Policy"] = "img-src 'self' data: blob:"
    return page


def install(app: FastAPI) -> None:
    """Serve the dashboard, its assets and the offline docs (create the app with
    ``docs_url=None, redoc_url=None``)."""
    app.mount("/static/docs", StaticFiles(directory=DOCS_ASSETS), name="docs-assets")
    app.mount("/static/dashboard", StaticFiles(directory=STATIC), name="dashboard-assets")
    app.include_router(api)
    app.include_router(router)

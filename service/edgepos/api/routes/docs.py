"""Swagger UI at /docs and ReDoc at /redoc, using assets shipped in the package (no CDN)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse

STATIC_PREFIX = "/static"
router = APIRouter(include_in_schema=False)

_FAVICON = f"{STATIC_PREFIX}/swagger-ui/favicon-32x32.png"


@router.get("/docs")
async def swagger_ui() -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="edgepos API",
        swagger_js_url=f"{STATIC_PREFIX}/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url=f"{STATIC_PREFIX}/swagger-ui/swagger-ui.css",
        swagger_favicon_url=_FAVICON,
        swagger_ui_parameters={"validatorUrl": None},
    )


@router.get("/redoc")
async def redoc() -> HTMLResponse:
    return get_redoc_html(
        openapi_url="/openapi.json",
        title="edgepos API",
        redoc_js_url=f"{STATIC_PREFIX}/redoc/redoc.standalone.js",
        redoc_favicon_url=_FAVICON,
        with_google_fonts=False,
    )

"""``GET /map``: the live operator map (a module not named ``map``: it would shadow the builtin in the
package ``edgepos.api.routes``), one page of the package's static files (no CDN, no map tiles).

The page itself holds no site or vehicle data: it asks for the admin key and reads the API with it
(GET /v1/status, /v1/rsus, /v1/sessions and the fix stream). Its Content-Security-Policy lets it load and
connect to this server only, so an edge box without Internet serves it whole, and a page that tried to
reach outside would be stopped by the browser.
"""

from __future__ import annotations

import functools
from importlib import resources

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

PATH = "/map"
router = APIRouter(include_in_schema=False)

CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
    "form-action 'none'; frame-ancestors 'none'; base-uri 'none'"
)
_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}


@functools.cache
def _page() -> str:
    return (resources.files("edgepos.api") / "static" / "map" / "index.html").read_text(encoding="utf-8")


@router.get(PATH)
async def operator_map() -> HTMLResponse:
    return HTMLResponse(_page(), headers=_HEADERS)

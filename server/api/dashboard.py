"""The operator dashboard (HMI): plain files from clients/hmi, served by the app itself.

`GET /` is the page (`index.html`); its style sheet and its scripts, ES
modules (`app.js` and what it imports; StaticFiles serves `.js` as JavaScript,
which module scripts require), are under `/hmi/...`. Nothing here is secret:
the page asks for a token and sends it as `Authorization: Bearer` on every API
call, like any other client. The page and its assets go through the same
gate as every request (`access.Access.check`: policy entry `("GET", "/")` and the
open prefix `/hmi/`, after the `trusted_networks` check). The page may only
talk to its own origin (Content-Security-Policy), so it fetches nothing from
elsewhere and cannot be framed by another site.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import Message, Receive, Scope, Send

HMI_DIR = Path(__file__).resolve().parents[2] / "clients" / "hmi"
PAGE_PATH = "/"
ASSETS_PATH = "/hmi"
ROUTE_NAME = "dashboard"

SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
        "style-src 'self'; script-src 'self'; object-src 'none'; base-uri 'none'; "
        "frame-ancestors 'none'; form-action 'self'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    # The files change with the server: revalidate (ETag) rather than run an old script.
    "Cache-Control": "no-cache",
}


class DashboardAssets(StaticFiles):
    """StaticFiles for the dashboard's assets, with the page's security headers."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers += [(k.lower().encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]
                message = {**message, "headers": headers}
            await send(message)

        await super().__call__(scope, receive, send_with_headers)


def mount_dashboard(app: FastAPI, directory: Path = HMI_DIR) -> None:
    """Serve the dashboard: the page at `/`, its assets under `/hmi/`. Idempotent."""
    if any(getattr(route, "name", None) == ROUTE_NAME for route in app.routes):
        return
    index = directory / "index.html"
    if not index.is_file():
        raise FileNotFoundError(f"the dashboard's page is missing: {index}")

    @app.get(
        PAGE_PATH,
        name=ROUTE_NAME,
        include_in_schema=False,
        response_class=FileResponse,
    )
    async def dashboard_page() -> FileResponse:
        """The operator dashboard (it asks for a token itself)."""
        return FileResponse(index, media_type="text/html", headers=SECURITY_HEADERS)

    app.mount(ASSETS_PATH, DashboardAssets(directory=directory), name="dashboard-assets")

"""Every route made ready at start-up, so the first stop pressed is not the one that pays.

Why: FastAPI prepares a route lazily, the first time a request is matched
against it (its fields, its body model's validator, what it depends on), and a
request is matched against every route before its own in the table. The first
POST /estop after a start would therefore prepare the routes ahead of it first:
milliseconds in the server before the devices are commanded, where every later
stop takes a fraction of one (tests/integration/test_first_stop.py).
`prepare_routes` matches one request that fits no route against the app's own
router at start-up, which walks, and so prepares, every route.

It goes to the router, not through the app: no middleware sees it, so there
is no audit row, no metric and no answer on any socket.
"""

from __future__ import annotations

from fastapi import FastAPI
from starlette.exceptions import HTTPException
from starlette.types import Message, Scope

NO_ROUTE = "/-/prepare-routes"  # a path no route of the app matches


async def prepare_routes(app: FastAPI) -> None:
    """Match a request for NO_ROUTE against every route of `app` (module docstring)."""
    scope: Scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "GET",
        "scheme": "http",
        "path": NO_ROUTE,
        "raw_path": NO_ROUTE.encode(),
        "root_path": "",
        "query_string": b"",
        "headers": [],
        "client": None,
        "server": None,
        "app": app,
    }

    async def receive() -> Message:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: Message) -> None:
        """Nothing is answered: the request came from no one."""

    try:
        await app.router(scope, receive, send)
    except HTTPException as not_found:  # inside an app, the router raises its 404
        if not_found.status_code != 404:
            raise

"""Every route made ready at start-up, so the first stop pressed is not the one that pays.

Why: FastAPI prepares a route lazily, the first time a request is matched
against it (its fields, its body model's validator, what it depends on), and a
request is matched against every route before its own in the table. The first
POST /estop after a start would therefore prepare the routes ahead of it first:
milliseconds in the server before the devices are commanded, where every later
stop takes a fraction of one (tests/integration/test_first_stop.py).
`prepare_routes` matches one request that fits no route against the app's own
router at start-up, which walks, and so prepares, every route.

It goes to the router's entries, not through the app: no middleware sees it, so
there is no audit row, no metric and no answer on any socket. One entry at a
time (a route, or a router the app includes with its routes), yielding to the
event loop between them: the app's start-up runs it beside the cell's
(`server/bootstrap/app.py`), whose devices connect meanwhile, and the
preparation of every route (a few hundred milliseconds) holds the loop for one
entry's share at most. The port opens once every route is prepared.
"""

from __future__ import annotations

import asyncio

from fastapi import FastAPI
from starlette.routing import Match
from starlette.types import Scope

NO_ROUTE = "/-/prepare-routes"  # a path no route of the app matches


async def prepare_routes(app: FastAPI) -> None:
    """Match a request for NO_ROUTE against every route of `app`, one after another
    (module docstring)."""
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

    for route in app.router.routes:
        match, _ = route.matches(scope)  # prepares the route, as the router's walk does
        if match is not Match.NONE:
            raise RuntimeError(f"{NO_ROUTE} was matched by {route!r}: pick another path")
        await asyncio.sleep(0)

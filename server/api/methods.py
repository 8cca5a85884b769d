"""HTTP manners the router leaves out: HEAD on every GET route, OPTIONS and 405 with Allow.

FastAPI routes answer only the methods they declare, so `HEAD /state` was a
405; and where several routes share a path (GET and POST /workpieces) the
router's 405 named only the first route's methods. `RouteMethods` reads which
methods each path answers from the app's own routes (the truth, not a second
list), and:

- the HTTP door (server/api/door.py), after the access check and the body
  limit, answers `HEAD` as the path's `GET` would (`without_body`), and
  `OPTIONS` with 204 and `Allow` (`answer_options`). Other methods pass
  straight through: a command pays one string comparison.
- `method_not_allowed` (the app's handler for 405) names every method of the
  path in `Allow`.

Who may ask is the gate's business (server/security/policy.py): HEAD needs
what GET needs, OPTIONS the least any of the path's methods needs.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.routing import Mount
from starlette.staticfiles import StaticFiles
from starlette.types import Message, Send

METHOD_ORDER = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")
STATIC_METHODS = frozenset({"GET", "HEAD"})  # what StaticFiles answers


def _http_routes(routes: Iterable[Any]) -> Iterator[tuple[re.Pattern[str], frozenset[str]]]:
    """(path regex, methods) of every HTTP route, included routers' routes too.

    FastAPI (0.16x) keeps an included router as one entry of `app.routes`
    whose routes are reached through `effective_route_contexts`; a mounted
    StaticFiles answers GET and HEAD under its prefix. WebSocket routes have
    no methods and are left out.
    """
    for route in routes:
        contexts = getattr(route, "effective_route_contexts", None)
        if contexts is not None:
            yield from _http_routes(contexts())
        elif isinstance(route, Mount) and isinstance(route.app, StaticFiles):
            yield route.path_regex, STATIC_METHODS
        elif getattr(route, "methods", None):
            yield route.path_regex, frozenset(route.methods)


class RouteMethods:
    """Which methods the app answers on a path, read from its routes when first asked.

    Read lazily because routes are added after the middleware is declared;
    by the first request the app is complete.
    """

    def __init__(self, app: Starlette) -> None:
        self._app = app
        self._routes: list[tuple[re.Pattern[str], frozenset[str]]] | None = None

    def allowed(self, path: str) -> frozenset[str]:
        """The methods some route answers on `path`, with HEAD and OPTIONS; empty if none."""
        if self._routes is None:
            self._routes = list(_http_routes(self._app.routes))
        methods = {m for pattern, ms in self._routes if pattern.match(path) for m in ms}
        if not methods:
            return frozenset()
        if "GET" in methods:
            methods.add("HEAD")
        return frozenset(methods | {"OPTIONS"})


def allow_header(methods: Iterable[str]) -> str:
    """`Allow`'s value, in a stable order."""
    given = set(methods)
    return ", ".join(m for m in METHOD_ORDER if m in given)


async def answer_options(send: Send, allowed: frozenset[str]) -> None:
    """OPTIONS' answer: 204 with `Allow`."""
    headers = [(b"allow", allow_header(allowed).encode("latin-1"))]
    await send({"type": "http.response.start", "status": 204, "headers": headers})
    await send({"type": "http.response.body", "body": b""})


def without_body(send: Send) -> Send:
    """GET's answer with its headers (Content-Length included) and none of its body."""

    async def send_head(message: Message) -> None:
        if message["type"] == "http.response.body":
            if message.get("more_body", False):
                return  # a streamed body: only its end is sent, empty
            message = {"type": "http.response.body", "body": b""}
        await send(message)

    return send_head


async def method_not_allowed(request: Request, exc: Exception) -> JSONResponse:
    """405 naming every method the path answers, in `Allow` and in the detail."""
    methods: RouteMethods = request.app.state.route_methods
    allowed = allow_header(methods.allowed(request.url.path))
    detail = exc.detail if isinstance(exc, HTTPException) else "method not allowed"
    if allowed:
        detail = f"{request.method} is not allowed on {request.url.path}; allowed: {allowed}"
    return JSONResponse({"detail": detail}, 405, headers={"Allow": allowed} if allowed else None)

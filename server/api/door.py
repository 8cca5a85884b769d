"""The HTTP door: the one ASGI middleware every HTTP request enters the app through.

Each request meets, in this order, what the app asks of every request before
routing, each kept in its own module and called here as a function that returns:

1. its response watched (server/api/observe.py, `ResponseWatch`): the command
   counted in flight until its answer is on the wire, and the observers (audit
   trail, metrics) told of the status once it has gone;
2. the access check (server/api/access.py, `Access.check`): network, token, and
   the role the policy names; a refusal is answered here, with no routing;
3. a stop (a POST to one of the catalogue's stop paths, as `is_stop` says) is
   handed to the stop lane (server/api/stop_lane.py), which halts the cell before its body
   is read and answers it; no other request enters the lane's module;
4. admission: a command (a POST to one of the catalogue's other command paths)
   has noted the e-stops counted as its headers were read (`ASKED_AT_ESTOPS`, by
   `on_headers`: one made after it refuses it, server/core/machine/decide.py) and
   waits here, before its body is read, while `ADMITTED` commands are being
   served, as on MQTT and OPC UA (the catalogue says why); a stop never waits for it;
5. the body limit (server/api/limits.py, `bounded`): a body over
   `max_request_bytes`, declared or streamed, is a 413;
6. the HTTP manners (server/api/methods.py): HEAD answered as GET without the
   body, OPTIONS with 204 and `Allow`;

then the request is handed on to the router. Why one middleware and not one per
concern: each ASGI layer is a frame and an `await` every request crosses, and
the checks read best in the order they apply, in one place. Only Starlette's
CORS middleware, when `cors_allowed_origins` is set, stands outside it. A
WebSocket or the lifespan passes straight through: the WebSocket proves who it
is in server/api/ws.py.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from server.api import limits, methods
from server.api.access import Access
from server.api.observe import Observer, ResponseWatch
from server.api.stop_lane import StopLane
from server.commands.catalogue import ADMITTED, COMMAND_PATHS, STOP_PATHS
from server.core.infra.answers_in_flight import AnswersInFlight

if TYPE_CHECKING:
    from server.bootstrap.cell import Cell


ASKED_AT_ESTOPS = "asked_at_estops"  # the scope state's key: the e-stops a command found


def on_headers(app: Any, scope: Scope) -> bool:
    """What the HTTP protocol asks the moment a request's headers are read, before
    the loop runs the work queued ahead of it (server/api/connection_guard.py):
    whether the request is a stop, which then goes first in the loop's line, so a
    flood on other connections holds it back no turn of the loop at all.

    A command notes the e-stops counted here, not at its turn in the door: a stop
    read after it that overtakes it in the line is still a stop made after it.
    Only for the app of a started cell; otherwise the door does it all in order.
    """
    if scope["method"] != "POST":  # most requests: nothing to note, nothing to hurry
        return False
    stop = is_stop(scope)
    if not stop and scope["path"] not in COMMAND_PATHS:
        return False
    cell = getattr(getattr(app, "state", None), "cell", None)
    if cell is None or not cell.started:
        return False
    if not stop:
        scope.setdefault("state", {})[ASKED_AT_ESTOPS] = cell.stops_now()
    return stop


def is_stop(scope: Scope) -> bool:
    """Whether this HTTP request is a stop (POST to a stop route): the one answer the
    door, the access check (a stop is never locked out) and the 422 handler use."""
    return scope["type"] == "http" and scope["method"] == "POST" and scope["path"] in STOP_PATHS


class HttpDoor:
    """ASGI middleware: every HTTP request's checks, in the order they apply
    (module docstring); the router behind it is `app`."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        access: Access,
        observers: list[Observer],
        answers: AnswersInFlight | None,
        route_methods: methods.RouteMethods,
        max_bytes: int,
    ) -> None:
        self.app = app
        self.access = access
        self.observers = observers
        self.answers = answers
        self.route_methods = route_methods
        self.max_bytes = max_bytes  # max_request_bytes
        self.stop_lane = StopLane(app, max_bytes)
        self.admitted = asyncio.Semaphore(ADMITTED)  # commands (not stops) served at once

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        watch = ResponseWatch(scope, send, self.answers)
        send = watch.send
        try:
            stop = is_stop(scope)
            refusal = self.access.check(scope, stop=stop)
            if refusal is not None:
                status, reason, headers = refusal
                scope.setdefault("state", {})["audit_reason"] = reason
                response = JSONResponse({"detail": reason}, status, headers=headers)
                await response(scope, receive, send)
                return
            cell: Cell | None = getattr(scope["app"].state, "cell", None)
            if stop:
                if cell is not None and cell.started:
                    await self.stop_lane.stop(cell.stops, scope, receive, send)
                    return
                # A cell not started yet: the stop goes on to its route, which makes it.
            elif scope["method"] == "POST" and scope["path"] in COMMAND_PATHS:
                if cell is not None and cell.started:  # refused if a stop comes ahead of it
                    scope.setdefault("state", {}).setdefault(ASKED_AT_ESTOPS, cell.stops_now())
                async with self.admitted:
                    await self._route(scope, receive, send)
                return
            await self._route(scope, receive, send)
        finally:
            watch.finish(scope, self.observers)

    async def _route(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The body limit and the HTTP manners, then the router."""
        bounded = limits.bounded(scope, receive, send, self.max_bytes)
        if bounded is None:
            await limits.refuse(scope, send, self.max_bytes)
            return
        receive, send = bounded
        method = scope["method"]
        if method == "HEAD" or method == "OPTIONS":
            await self._manners(scope, receive, send)
            return
        await self.app(scope, receive, send)

    async def _manners(self, scope: Scope, receive: Receive, send: Send) -> None:
        """HEAD as the path's GET without its body; OPTIONS answered with `Allow`."""
        method = scope["method"]
        allowed = self.route_methods.allowed(scope["path"])
        if method == "OPTIONS" and allowed:
            await methods.answer_options(send, allowed)
            return
        if method == "HEAD" and "GET" in allowed:
            as_get = {**scope, "method": "GET"}  # a copy: the server's scope stays HEAD
            try:
                await self.app(as_get, receive, methods.without_body(send))
            finally:
                if "route" in as_get:  # for the metrics' route label
                    scope["route"] = as_get["route"]
            return
        await self.app(scope, receive, send)

"""The e-stop's HTTP side: which requests are stops, and their halt made at the gate.

The stop routes are the command catalogue's (`STOP_PATHS`: the paths of its
entries marked `stop`, server/commands/catalogue.py), and `is_stop` the one
answer to "is this request a stop": the access gate (never locked out), the
body limit (never refused over its body), this lane and the route's 422 all
ask it; openapi.json reads the same `STOP_PATHS`.

Why the halt is made here: between the access gate and the stop's handler a
request crosses FastAPI's routing, the validation of its (optional) body and
the handler's own steps: most of the time from the request's arrival to the
halt's commands (docs/benchmarks.md, "Software stop"). The lane begins the stop
instead, once the gate has let the request through (so only a token allowed to
stop can stop): `EmergencyStops.begin` (server/core/worker/stop.py) counts the
stop, cuts the run's leash and writes both halt commands' frames. The route
then finishes that `Stop` with its reason and audit note, and answers.

A halt is never left without its transition: if the route did not get to
finish the stop (an error on the way), the lane posts the EMERGENCY_STOP
itself, so the cell still goes to ERROR and the stop is on record.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable
from typing import TYPE_CHECKING

from starlette.types import ASGIApp, Receive, Scope, Send

from server.commands.catalogue import STOP_PATHS

if TYPE_CHECKING:
    from server.bootstrap.cell import Cell
    from server.core.worker.stop import EmergencyStops, Stop

log = logging.getLogger(__name__)


# Where the lane leaves the stop it began in the request's state, for the route.
STOP_BEGUN = "stop_begun"


def is_stop(scope: Scope) -> bool:
    """Whether this HTTP request is a stop (POST to a stop route)."""
    return scope["type"] == "http" and scope["method"] == "POST" and scope["path"] in STOP_PATHS


class StopLane:
    """ASGI middleware, inside the access gate: a stop request halts the devices now."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    def __call__(self, scope: Scope, receive: Receive, send: Send) -> Awaitable[None]:
        """Not a coroutine: any other request is handed on as it is, with no frame of ours."""
        stops = _stops_of(scope) if is_stop(scope) else None
        if stops is None:
            return self.app(scope, receive, send)
        return self._stop(stops, scope, receive, send)

    async def _stop(
        self, stops: EmergencyStops, scope: Scope, receive: Receive, send: Send
    ) -> None:
        stop = stops.begin()
        scope.setdefault("state", {})[STOP_BEGUN] = stop
        try:
            await self.app(scope, receive, send)
        finally:
            if not stop.posted:  # the route did not finish the stop: post it here
                log.error("the stop route failed before it made the stop; made by the lane")
                stop.post(source=source_of(scope))


def source_of(scope: Scope) -> str:
    """Who sent a command over the API, as its event's `source` says it: `api:<token name>`.

    The token's name is what a person at the panel knows the sender by ("line 3 HMI"),
    so a stop reason built from it says who stopped the cell. The address stays in the
    audit row (server/api/audit.py), not here. Without a principal (a server with no
    gate, in tests): `api:<host>`.
    """
    principal = scope.get("state", {}).get("principal")
    if principal is not None:
        return f"api:{principal.name}"
    client = scope.get("client")
    return f"api:{client[0] if client else 'unknown'}"


def stop_begun(scope: Scope) -> Stop | None:
    """The stop the lane began for this request, if it did (the cell was started)."""
    stop: Stop | None = scope.get("state", {}).get(STOP_BEGUN)
    return stop


def _stops_of(scope: Scope) -> EmergencyStops | None:
    cell: Cell | None = getattr(scope["app"].state, "cell", None)
    return cell.stops if cell is not None and cell.started else None

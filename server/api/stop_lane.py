"""The e-stop's halt, made as its request passes the gate: before routing and its body.

Why: between the access gate and the stop's handler a request crosses FastAPI's
routing, the validation of its (optional) body and the handler's own steps:
most of the time from the request's arrival to the halt's commands
(docs/benchmarks.md, "Software stop"). The devices are commanded here instead, once
the gate has let the request through (so only a token allowed to stop can stop):
`Worker.halt_for_stop` counts the stop, cuts the run's leash and writes both halt
commands' frames (tasks started at once: no turn of the loop comes first). The
route then makes the stop with that halt, with its reason, its audit row and
its answer.

A halt is never left without its transition: if the route did not get to the
stop (an error on the way), the lane queues the EMERGENCY_STOP itself, so the
cell still goes to ERROR and the stop is on record.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Iterable
from typing import TYPE_CHECKING

from starlette.types import ASGIApp, Receive, Scope, Send

if TYPE_CHECKING:
    from server.bootstrap.cell import Cell
    from server.core.worker.devices import HaltReport
    from server.core.worker.worker import Worker

log = logging.getLogger(__name__)

# Where the lane leaves the halt in the request's state, for the route to take.
HALT_MADE = "stop_halt_made"


class StopLane:
    """ASGI middleware, inside the access gate: POST to a stop path halts the devices now."""

    def __init__(self, app: ASGIApp, stop_paths: Iterable[str]) -> None:
        self.app = app
        self.stop_paths = frozenset(stop_paths)

    def __call__(self, scope: Scope, receive: Receive, send: Send) -> Awaitable[None]:
        """Not a coroutine: any other request is handed on as it is, with no frame of ours."""
        worker = _worker_of(scope) if _is_stop(scope, self.stop_paths) else None
        if worker is None:
            return self.app(scope, receive, send)
        return self._stop(worker, scope, receive, send)

    async def _stop(self, worker: Worker, scope: Scope, receive: Receive, send: Send) -> None:
        state = scope.setdefault("state", {})
        state[HALT_MADE] = worker.halt_for_stop()
        try:
            await self.app(scope, receive, send)
        finally:
            halt = state.pop(HALT_MADE, None)
            if halt is not None:  # the route did not make the stop: make it here
                log.error("the stop route failed before it made the stop; made by the lane")
                worker.post_stop(halt, source=source_of(scope))


def source_of(scope: Scope) -> str:
    """Who sent a command over the API, as its event's `source` says it: `api:<host>`."""
    client = scope.get("client")
    return f"api:{client[0] if client else 'unknown'}"


def take_halt(scope: Scope) -> asyncio.Future[HaltReport] | None:
    """The halt the lane made for this request (once: whoever takes it makes the stop)."""
    halt: asyncio.Future[HaltReport] | None = scope.get("state", {}).pop(HALT_MADE, None)
    return halt


def _is_stop(scope: Scope, stop_paths: frozenset[str]) -> bool:
    return scope["type"] == "http" and scope["method"] == "POST" and scope["path"] in stop_paths


def _worker_of(scope: Scope) -> Worker | None:
    cell: Cell | None = getattr(scope["app"].state, "cell", None)
    return cell.worker if cell is not None else None

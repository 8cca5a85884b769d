"""The e-stop's HTTP side: each stop made and answered here.

Which requests are stops the HTTP door decides (server/api/door.py: `is_stop`,
POST to a path of the catalogue's `STOP_PATHS`); it hands each one here once the
access check has let it through, and no other request enters this module.

Why the stop is made here, as the request arrives, and not in its route: between
the access check and a route a request crosses the body limit,
FastAPI's routing, the reading and validation of its body and the handler's
own steps, most of the time from the request's arrival to the halt's commands
(docs/benchmarks.md, "Software stop"), and a body slow to arrive would hold the
halt back. Once the gate has let the request through (only a token allowed to
stop can stop), the lane:

1. begins the stop (`EmergencyStops.begin`, server/core/worker/stop.py: the
   stop counted, the run's leash cut, both halt frames written), before a byte
   of the body is read;
2. reads the body whole, up to `max_request_bytes` (a stop is never refused
   over its body: one too large is not read, and the stop is made without its
   reason);
3. finishes the stop with the body's reason (`Stop.finish`: its event in the
   queue's top lane, answered once the worker has decided it and it is on
   record) and answers: 202, or 413 for a body too large, with what the cell did.

So a stop never passes the body limit (server/api/limits.py, which the door
asks after the lane), the router or the route. A body the lane cannot take as the route's
request model would (not JSON, a field wrong) goes on to the route with the
stop begun (`stop_begun`), where FastAPI words the 422 as for every command and
`commands.stop_anyway` finishes the stop. Whatever happens on the way, a halt
is never left without its transition: if the stop was not finished, the lane
posts its EMERGENCY_STOP itself, so the cell still goes to ERROR, on record.
"""

from __future__ import annotations

import json
import logging
from email.message import Message as MimeHeader
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ValidationError
from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api import audit
from server.api.audit import source_of
from server.commands.answers import answer_of, audit_label
from server.commands.catalogue import CATALOGUE, CommandSpec
from server.core.machine.events import StopPayload

if TYPE_CHECKING:
    from server.core.worker.stop import EmergencyStops, Stop

log = logging.getLogger(__name__)


# Where the lane leaves a stop it began but the route must finish, in the request's state.
STOP_BEGUN = "stop_begun"
# The catalogue's stop entries by path: each one's request model and payload builder.
_STOP_SPECS: dict[str, CommandSpec] = {spec.path: spec for spec in CATALOGUE if spec.stop}


class StopLane:
    """A stop request halts, is decided and answered here (module docstring); the HTTP
    door hands it each stop once the access check has let it through."""

    def __init__(self, route: ASGIApp, max_bytes: int) -> None:
        self.route = route  # where a body to refuse goes on to (the router)
        self.max_bytes = max_bytes  # max_request_bytes: the most of a stop's body read

    async def stop(self, stops: EmergencyStops, scope: Scope, receive: Receive, send: Send) -> None:
        """Begin the stop, read its body, finish it and answer (or hand a body to refuse
        on to the route, the stop begun)."""
        stop = stops.begin()
        try:
            body = await self._read_whole(scope, receive)
            if body is None:  # too large to read: stopped all the same, and the 413 says so
                why = f"request body over {self.max_bytes} bytes, not read"
                _status, answer, _headers = await self._finish(stop, scope, StopPayload(None))
                answer = {"detail": why, **made_without_reason(answer)}
                await JSONResponse(answer, status_code=413)(scope, receive, send)
                return
            payload = _payload_of(_STOP_SPECS[scope["path"]], scope, body)
            if payload is None:  # the route's validation words what is wrong (422)
                scope.setdefault("state", {})[STOP_BEGUN] = stop
                await self.route(scope, _replaying(body, receive), send)
                return
            status, answer, headers = await self._finish(stop, scope, payload)
            await JSONResponse(answer, status_code=status, headers=headers or None)(
                scope, receive, send
            )
        finally:
            if not stop.posted:  # not finished on its way (an error): posted here
                log.error("the stop failed before it was finished; its event posted by the lane")
                stop.post(source=source_of(scope))

    async def _finish(
        self, stop: Stop, scope: Scope, payload: StopPayload
    ) -> tuple[int, dict[str, Any], dict[str, str]]:
        """The stop's event posted with its reason and audit note; its answer once decided."""
        outcome = await stop.finish(
            source=source_of(scope), payload=payload, audit=audit.note(scope, audit_label)
        )
        audit.answered(scope, outcome)
        return answer_of(outcome)

    async def _read_whole(self, scope: Scope, receive: Receive) -> bytes | None:
        """The whole body, or None if it is over the limit (then not read further).

        Read whole before anything looks at it (bounded by the limit), so the stop
        gets either the bytes sent or no reason, never a truncated document. A
        client gone before its body ended sent none.
        """
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            return None
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return b""
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                return b"".join(chunks)


def made_without_reason(answer: dict[str, Any]) -> dict[str, Any]:
    """What a 4xx says the cell did when its stop was made without the body's reason."""
    answer = dict(answer)
    answer["message"] = f"the stop was made without its reason: {answer.get('message', '')}"
    return {k: answer[k] for k in ("accepted", "event_id", "state", "message") if k in answer}


def _payload_of(spec: CommandSpec, scope: Scope, body: bytes) -> StopPayload | None:
    """The stop's payload from its body, taken as the route would take it; None when the
    route would refuse the body (then the route does, and says why).

    As FastAPI reads a body: none is no request model; JSON when the content type is
    application/json (or +json), else bytes no model accepts (FastAPI's strict content
    type, its default: a body without a content type is not read as JSON either).
    """
    parsed: Any = None
    if body:
        if not _is_json(scope):
            return None
        try:
            parsed = json.loads(body)
        except ValueError:
            return None
    model: BaseModel | None = None
    if parsed is not None and spec.request is not None:
        try:
            model = spec.request.model_validate(parsed)
        except ValidationError:
            return None
    payload = spec.payload(model) if spec.payload is not None else None
    return payload if isinstance(payload, StopPayload) else StopPayload()


def _is_json(scope: Scope) -> bool:
    content_type = Headers(scope=scope).get("content-type")
    if not content_type:
        return False
    header = MimeHeader()
    header["content-type"] = content_type
    subtype = header.get_content_subtype()
    return header.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


def _replaying(body: bytes, receive: Receive) -> Receive:
    """`receive` with the body already read given back first, whole."""
    given = False

    async def replay() -> Message:
        nonlocal given
        if given:
            return await receive()
        given = True
        return {"type": "http.request", "body": body, "more_body": False}

    return replay


def stop_begun(scope: Scope) -> Stop | None:
    """The stop the lane began and handed on to the route for this request, if it did."""
    stop: Stop | None = scope.get("state", {}).get(STOP_BEGUN)
    return stop

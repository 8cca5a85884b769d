"""Command routes: one POST route per catalogue entry, each posting its event.

Every route is declared from server/commands/catalogue.py (path `/<name>`,
operationId, summary, description, request model); none is written by hand, so
a new command is a new entry there. A route answers once the worker has decided:
202 when accepted; 409 when the current state refuses it or what the command
needs first is missing (a calibration, a part in the library), with what to do;
422 naming the field when the request itself is wrong (start without contour
matching names no workpiece); 503 with Retry-After when the event queue is
full, or when the journal cannot write: an answer is never a 202 for what is
not on record. A refusal changes nothing and is journaled and audited like any
command; the audit row is committed with the event, before the answer.
The e-stop's route is declared here like the others (openapi.json, the
policy), but a stop is made and answered before the router, by the stop lane
the HTTP door hands it to (server/api/door.py, server/api/stop_lane.py): it
halts the devices first, then posts the event ahead of everything waiting; a
202 once the cell has stopped, even when the journal could not record it (the
message says so). The route finishes a stop
only when the lane handed it on: a body to refuse (422, `stop_anyway`), or a
cell not started when the request passed the lane.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import APIRouter, Body, Request, Response
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute

from server.api import audit
from server.api.audit import source_of
from server.api.declared_query import IGNORES_UNKNOWN_QUERY, Handler, query_check_of
from server.api.door import ASKED_AT_ESTOPS
from server.api.stop_lane import made_without_reason, stop_begun
from server.bootstrap.cell import Cell
from server.commands.answers import answer_of, audit_label
from server.commands.catalogue import CATALOGUE, CommandSpec
from server.commands.requests import CommandResult, QueueFullResult
from server.core.machine.events import Outcome, Payload, StopPayload
from server.core.machine.transitions import Command

__all__ = ["router", "stop_anyway"]


class CommandRoute(APIRoute):
    """A catalogue entry's route: a query parameter it does not declare is a 422
    (server/api/declared_query.py's `QueryCheck`, asked here before FastAPI reads the
    body, as every route of the app asks it), then FastAPI's own handler."""

    def get_route_handler(self) -> Handler:
        handler = super().get_route_handler()
        check = query_check_of(self)
        if check is None:  # a stop: never refused over a query parameter
            return handler

        async def command(request: Request) -> Response:
            if request.scope["query_string"]:
                check(request)
            return await handler(request)

        return command


router = APIRouter(tags=["commands"], route_class=CommandRoute)

RESPONSES: dict[int | str, dict[str, Any]] = {
    202: {"model": CommandResult, "description": "accepted: the machine changed state"},
    409: {
        "model": CommandResult,
        "description": "refused: not allowed in the current state, or what the command needs "
        "first is missing (the message says what to do); nothing changed",
    },
    503: {
        "model": QueueFullResult,
        "description": "the event queue is full, or the journal cannot write (a full disk: "
        "then a command already decided stops the cell, JOURNAL_WRITE_FAILED); retry later",
    },
}


def _cell(request: Request) -> Cell:
    return request.app.state.cell


def _answer(status: int, body: dict[str, Any], headers: dict[str, str]) -> JSONResponse:
    return JSONResponse(body, status_code=status, headers=headers or None)


async def _run(request: Request, command: Command, payload: Payload | None = None) -> JSONResponse:
    outcome = await _cell(request).command(
        command,
        source=source_of(request.scope),
        payload=payload,
        audit=audit.note(request.scope, audit_label),
        asked_at_estops=request.scope.get("state", {}).get(ASKED_AT_ESTOPS),
    )
    return _answered(request, outcome)


async def _stop(request: Request, payload: StopPayload) -> JSONResponse:
    """Finish the stop the stop lane began and handed on (one is made here if it did
    not: the cell was not started when the request passed the lane)."""
    stop = stop_begun(request.scope) or _cell(request).stops.begin()
    outcome = await stop.finish(
        source=source_of(request.scope),
        payload=payload,
        audit=audit.note(request.scope, audit_label),
    )
    return _answered(request, outcome)


def _answered(request: Request, outcome: Outcome) -> JSONResponse:
    audit.answered(request.scope, outcome)
    return _answer(*answer_of(outcome))


def _endpoint(spec: CommandSpec) -> Callable[..., Awaitable[JSONResponse]]:
    """The route function of one catalogue entry, its signature built from the entry.

    FastAPI reads the signature: a command with a request model takes it as the
    body (optional unless the entry says it is required), the others none.
    """

    async def endpoint(request: Request, body: Any = None) -> JSONResponse:
        if not spec.stop:
            payload = spec.payload(body) if spec.payload is not None else None
            return await _run(request, spec.command, payload)
        stop = spec.payload(body) if spec.payload is not None else None
        return await _stop(request, stop if isinstance(stop, StopPayload) else StopPayload())

    parameters = [
        inspect.Parameter("request", inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=Request)
    ]
    if spec.request is not None:
        kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
        if spec.body_required:
            parameters.append(inspect.Parameter("body", kind, annotation=spec.request))
        else:
            optional = Annotated[spec.request | None, Body()]  # type: ignore[name-defined]
            parameters.append(inspect.Parameter("body", kind, annotation=optional, default=None))
    endpoint.__signature__ = inspect.Signature(parameters, return_annotation=JSONResponse)  # type: ignore[attr-defined]
    endpoint.__name__ = endpoint.__qualname__ = spec.name.replace("-", "_")
    endpoint.__doc__ = spec.description
    return endpoint


for _spec in CATALOGUE:
    router.add_api_route(
        _spec.path,
        _endpoint(_spec),
        methods=["POST"],
        status_code=202,
        responses=RESPONSES,
        response_model=CommandResult,
        summary=_spec.summary,
        description=_spec.description,
        operation_id=_spec.operation_id,
        # A stop is never refused over a query parameter it does not read.
        openapi_extra={IGNORES_UNKNOWN_QUERY: True} if _spec.stop else None,
    )


async def stop_anyway(request: Request) -> dict[str, Any]:
    """Make the e-stop whose body was invalid (no reason recorded).

    The gate has let the request through (the role is checked before routing),
    so only the optional reason was wrong: refusing the stop over it would be
    the wrong way round. The answer stays a 4xx (the request was wrong: 422),
    with what the cell did beside it.
    """
    response = await _stop(request, StopPayload(None))
    return made_without_reason(json.loads(bytes(response.body)))

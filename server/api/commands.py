"""Command routes: each posts one event and answers once the worker has decided.

202 when accepted; 409 when the current state refuses it or what the command
needs first is missing (a calibration, a part in the library), with what to do;
422 naming the field when the request itself is wrong (start without contour
matching names no workpiece); 503 with Retry-After when the event queue is
full, or when the journal cannot write: an answer is never a 202 for what is
not on record. A refusal changes nothing and is journaled and audited like any
command; the audit row is committed with the event, before the answer.
The e-stop route does not queue behind anything: it halts the devices first,
then posts the event ahead of everything waiting; it is a 202 once the cell
has stopped, even when the journal could not record it (the message says so).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Annotated, Any

from fastapi import APIRouter, Body, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError

from server.api import audit
from server.api.declared_query import IGNORES_UNKNOWN_QUERY, DeclaredQueryRoute
from server.api.schemas import (
    RETRY_AFTER_S,
    CommandResult,
    CreateWorkpieceRequest,
    EstopRequest,
    JogRequest,
    QueueFullResult,
    StartRequest,
)
from server.api.stop_lane import source_of, stop_begun
from server.bootstrap.cell import Cell
from server.core.machine.events import (
    CreateWorkpiecePayload,
    JogPayload,
    Outcome,
    Payload,
    StartPayload,
    StopPayload,
)
from server.core.machine.transitions import Command, Event

router = APIRouter(tags=["commands"], route_class=DeclaredQueryRoute)

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


_UNRECORDED_ADVICE = {
    True: "a command must be on record, so the cell stops (JOURNAL_WRITE_FAILED): free space "
    "under the data directory, then reset",
    False: "nothing was changed: free space under the data directory, then try again",
}


def _status(outcome: Outcome) -> int:
    """The HTTP status of the worker's answer; the audit row says the same."""
    if outcome.journal_problem is not None and outcome.event is not Event.EMERGENCY_STOP:
        return 503  # not on record: never a 202 (the e-stop has stopped the cell regardless)
    if outcome.accepted:
        return 202
    return 422 if outcome.field is not None else 409


def audit_label(outcome: Outcome) -> str:
    """The outcome column of a command's audit row, from its HTTP status."""
    status = _status(outcome)
    return "accepted" if status < 400 else f"refused ({status})"


def answer_of(outcome: Outcome) -> tuple[int, dict[str, Any], dict[str, str]]:
    """The status, JSON body and headers that answer a command, whichever door it came by."""
    status = _status(outcome)
    if status == 503:
        unrecorded = {
            "accepted": outcome.accepted,
            "event_id": outcome.event_id,
            "state": outcome.state.value,
            "message": f"{outcome.message}; {_UNRECORDED_ADVICE[outcome.accepted]}",
            "retry_after": RETRY_AFTER_S,
        }
        return 503, unrecorded, {"Retry-After": str(RETRY_AFTER_S)}
    if status == 422:
        # The request names something wrong: a 422 like any invalid field, with the
        # cell's answer beside it (nothing changed).
        problem = {"field": outcome.field, "message": outcome.message, "type": "precondition"}
        refused = {
            "detail": f"invalid request: {outcome.field}: {outcome.message}",
            "errors": [problem],
            "accepted": False,
            "event_id": outcome.event_id,
            "state": outcome.state.value,
        }
        return 422, refused, {}
    body = CommandResult(
        accepted=outcome.accepted,
        event_id=outcome.event_id,
        state=outcome.state.value,
        message=outcome.message,
        run_id=outcome.run_id,
    )
    return status, body.model_dump(), {}


def _answer(outcome: Outcome) -> JSONResponse:
    status, body, headers = answer_of(outcome)
    return JSONResponse(body, status_code=status, headers=headers or None)


# Each command's request body (None: it takes none) and the payload the worker gets from
# it: the routes below and the MQTT door (server/mqtt/commands.py) build payloads here.
def start_payload(body: StartRequest | None) -> StartPayload:
    body = body or StartRequest()
    return StartPayload(body.contour_matching, body.workpiece_id)


def create_workpiece_payload(body: CreateWorkpieceRequest | None) -> CreateWorkpiecePayload:
    body = body or CreateWorkpieceRequest()
    spray = body.spray.model_dump(exclude_none=True) if body.spray is not None else None
    return CreateWorkpiecePayload(body.name, body.workpiece_id, spray)


def estop_payload(body: EstopRequest | None) -> StopPayload:
    return StopPayload(body.reason if body else None)


def jog_payload(body: JogRequest) -> JogPayload:
    return JogPayload(body.axis, body.distance_mm)


REQUEST_BODIES: dict[Command, tuple[type[BaseModel], Callable[[Any], Payload]]] = {
    Command.START: (StartRequest, start_payload),
    Command.CREATE_WORKPIECE: (CreateWorkpieceRequest, create_workpiece_payload),
    Command.ESTOP: (EstopRequest, estop_payload),
    Command.JOG: (JogRequest, jog_payload),
}


# One way a request is wrong, as a 422 names it: {"field", "message", "type"}.
Problem = dict[str, str]


def problem_of(error: Mapping[str, Any]) -> Problem:
    """One pydantic error as every door words it: the dotted field (HTTP's leading
    "body" left out), pydantic's message (never the value: it may be megabytes, or
    characters that would rewrite a log line), and its type."""
    where = ".".join(str(part) for part in error["loc"] if part != "body") or "body"
    return {"field": where, "message": str(error["msg"]), "type": str(error["type"])}


def invalid_request(problems: list[Problem]) -> str:
    """The 422's detail, which is also the refusal's audit detail, on every door."""
    return "invalid request: " + "; ".join(f"{p['field']}: {p['message']}" for p in problems)


def payload_of(command: Command, body: Any) -> tuple[Payload | None, list[Problem]]:
    """The worker's payload from a command's body, checked by the HTTP route's own model.

    The one validation every door shares: MQTT (server/mqtt/commands.py) and OPC UA
    (server/opcua/methods.py) call it with the body they were given (None: none), HTTP
    has FastAPI check the same model and build the payload with the same function, so
    a body is refused alike, with the same fields named, whichever way it came. A
    command that takes no body gets None, whatever was sent (as HTTP does not read it).
    """
    declared = REQUEST_BODIES.get(command)
    if declared is None:
        return None, []
    model, build = declared
    try:
        parsed: BaseModel = model.model_validate({} if body is None else body)
    except ValidationError as exc:
        return None, [problem_of(error) for error in exc.errors()]
    return build(parsed), []


def command_path(command: Command) -> str:
    """The HTTP route of a command: its role in server/security/policy.py is keyed on it."""
    return f"/{command.value}"


async def _run(request: Request, command: Command, payload: Payload | None = None) -> JSONResponse:
    outcome = await _cell(request).command(
        command,
        source=source_of(request.scope),
        payload=payload,
        audit=audit.note(request, audit_label),
    )
    return _answered(request, outcome)


async def _stop(request: Request, payload: StopPayload) -> JSONResponse:
    """Finish the stop the stop lane began as the request passed the gate (one is made
    here if it did not: the cell was not started then)."""
    stop = stop_begun(request.scope) or _cell(request).stops.begin()
    outcome = await stop.finish(
        source=source_of(request.scope),
        payload=payload,
        audit=audit.note(request, audit_label),
    )
    return _answered(request, outcome)


def _answered(request: Request, outcome: Outcome) -> JSONResponse:
    if outcome.journal_problem is None:
        request.state.audited = True  # its row was committed with the event
    else:  # not on record: the observer tries once more, with why
        request.state.audit_reason = f"event {outcome.event_id}: {outcome.message}"
    return _answer(outcome)


@router.post("/start", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def start(
    request: Request, body: Annotated[StartRequest | None, Body()] = None
) -> JSONResponse:
    """Start spraying (IDLE → EXECUTING_TRAJECTORY)."""
    return await _run(request, Command.START, start_payload(body))


@router.post("/calibrate-robot", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def calibrate_robot(request: Request) -> JSONResponse:
    """Calibrate camera → robot coordinates from the ArUco markers (IDLE → CALIBRATING_ROBOT)."""
    return await _run(request, Command.CALIBRATE_ROBOT)


@router.post(
    "/calibrate-camera", status_code=202, responses=RESPONSES, response_model=CommandResult
)
async def calibrate_camera(request: Request) -> JSONResponse:
    """Calibrate the camera's intrinsics (IDLE → CALIBRATING_CAMERA)."""
    return await _run(request, Command.CALIBRATE_CAMERA)


@router.post(
    "/create-workpiece", status_code=202, responses=RESPONSES, response_model=CommandResult
)
async def create_workpiece(
    request: Request, body: Annotated[CreateWorkpieceRequest | None, Body()] = None
) -> JSONResponse:
    """Capture the part on the table into the library (IDLE → CREATING_WORKPIECE)."""
    return await _run(request, Command.CREATE_WORKPIECE, create_workpiece_payload(body))


@router.post("/pause", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def pause(request: Request) -> JSONResponse:
    """Stop the trajectory where it is: valve closed and robot still before PAUSED is answered."""
    return await _run(request, Command.PAUSE)


@router.post("/resume", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def resume(request: Request) -> JSONResponse:
    """Continue a paused trajectory: back to where the robot stopped, then the same segment."""
    return await _run(request, Command.RESUME)


@router.post("/cancel", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def cancel(request: Request) -> JSONResponse:
    """Stop the running operation at once, glue off, and return to IDLE."""
    return await _run(request, Command.CANCEL)


@router.post(
    "/estop",
    status_code=202,
    responses=RESPONSES,
    response_model=CommandResult,
    # A stop is never refused over a query parameter it does not read.
    openapi_extra={IGNORES_UNKNOWN_QUERY: True},
)
async def estop(
    request: Request, body: Annotated[EstopRequest | None, Body()] = None
) -> JSONResponse:
    """Software stop: valve closed and robot stopped at once, then ERROR.

    A supervisory stop, not a safety function: the hard-wired e-stop circuit
    remains the cell's safety stop.
    """
    dropped = getattr(request.state, "body_dropped", None)
    if dropped is not None:  # too large to read: the stop is made, the 413 says so
        return JSONResponse({"detail": dropped, **await stop_anyway(request)}, status_code=413)
    return await _stop(request, estop_payload(body))


async def stop_anyway(request: Request) -> dict[str, Any]:
    """Make the e-stop whose body was invalid or too large (no reason recorded).

    The gate has let the request through (the role is checked before routing),
    so only the optional reason was wrong: refusing the stop over it would be
    the wrong way round. The answer stays a 4xx (the request was wrong: 422 or
    413), with what the cell did beside it.
    """
    response = await _stop(request, StopPayload(None))
    answer = json.loads(bytes(response.body))
    answer["message"] = f"the stop was made without its reason: {answer.get('message', '')}"
    return {k: answer[k] for k in ("accepted", "event_id", "state", "message") if k in answer}


@router.post("/reset", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def reset(request: Request) -> JSONResponse:
    """Leave ERROR for IDLE, once every device answers again; never restarts an operation."""
    return await _run(request, Command.RESET)


@router.post("/home", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def home(request: Request) -> JSONResponse:
    """Send the robot to its safe position (IDLE, stays IDLE; target checked first).

    The only way the robot moves outside an operation: nothing else (a reset,
    a restart, the end of a run) moves it by itself.
    """
    return await _run(request, Command.HOME)


@router.post("/jog", status_code=202, responses=RESPONSES, response_model=CommandResult)
async def jog(request: Request, body: JogRequest) -> JSONResponse:
    """Move the robot one bounded step along one axis, at jog speed (IDLE, stays IDLE).

    For maintenance teaching marker positions. Refused unless IDLE (409); a step
    longer than jog_max_step_mm or a target outside the workspace is a 422 naming
    `distance_mm`, checked against the pose the worker reads before anything moves.
    Answered once the step has begun, like home; the e-stop or a fault stops it.
    """
    return await _run(request, Command.JOG, jog_payload(body))

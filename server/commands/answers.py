"""How a command's body becomes the worker's payload, and its outcome an answer.

One validation and one answer for every door: HTTP, MQTT and OPC UA check a
body with the command's own request model (`payload_of`), word a wrong body the
same way (`problem_of`, `invalid_request`), and give the worker's `Outcome` the
same status, body and audit label (`answer_of`, `audit_label`); OPC UA maps the
status onto its own codes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ValidationError

from server.commands.catalogue import spec_of
from server.commands.requests import RETRY_AFTER_S, CommandResult
from server.core.machine.events import Outcome, Payload
from server.core.machine.transitions import Command, Event

_UNRECORDED_ADVICE = {
    True: "a command must be on record, so the cell stops (JOURNAL_WRITE_FAILED): free space "
    "under the data directory, then reset",
    False: "nothing was changed: free space under the data directory, then try again",
}


def status_of(outcome: Outcome) -> int:
    """The HTTP status of the worker's answer; the audit row says the same.

    503 when the decision is not on record (never a 202 for that: the e-stop has
    stopped the cell regardless, so it keeps its 202), 202 when accepted, 422 when
    the refusal names a field of the request, else 409.
    """
    if outcome.journal_problem is not None and outcome.event is not Event.EMERGENCY_STOP:
        return 503
    if outcome.accepted:
        return 202
    return 422 if outcome.field is not None else 409


def audit_label(outcome: Outcome) -> str:
    """The outcome column of a command's audit row, from its HTTP status."""
    status = status_of(outcome)
    return "accepted" if status < 400 else f"refused ({status})"


def answer_of(outcome: Outcome) -> tuple[int, dict[str, Any], dict[str, str]]:
    """The status, JSON body and headers that answer a command, whichever door it came by."""
    status = status_of(outcome)
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
    """The worker's payload from a command's body, checked by the command's own model.

    The one validation every door shares: MQTT and OPC UA call it with the body they
    were given (None: none); HTTP has FastAPI check the same model and build the
    payload with the same function, so a body is refused alike, with the same fields
    named, whichever way it came. A command that takes no body gets None, whatever
    was sent (as HTTP does not read it).
    """
    spec = spec_of(command)
    if spec.request is None or spec.payload is None:
        return None, []
    try:
        parsed: BaseModel = spec.request.model_validate({} if body is None else body)
    except ValidationError as exc:
        return None, [problem_of(error) for error in exc.errors()]
    return spec.payload(parsed), []

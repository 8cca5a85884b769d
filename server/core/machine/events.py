"""What each event carries: one frozen dataclass payload per kind of event.

An event's payload is typed, so the worker, the operations and the journal
agree on its fields by construction rather than by agreed dict keys.
`as_dict()` is the payload as the journal stores it (the `data` column of
`events`) and as an operation sees its parameters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, Final

from server.core.machine.transitions import Event, State
from server.core.operations.base import OperationResult


@dataclass(frozen=True, slots=True)
class Outcome:
    """The worker's answer to one event: what the sender of a command is told."""

    accepted: bool
    event_id: str
    event: Event
    state: State
    message: str
    field: str | None = None  # a refusal because this field of the request is wrong (HTTP 422)
    # Why the journal could not record this event (then it must not be answered as done).
    journal_problem: str | None = None
    # The run this event started (its event id), so the sender can follow that run.
    run_id: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "accepted": self.accepted,
            "event_id": self.event_id,
            "event": self.event.value,
            "state": self.state.value,
            "message": self.message,
        }

    def with_note(self, note: str) -> Outcome:
        """The same answer with `note` added to its message."""
        return replace(self, message=f"{self.message}{note}")

    def not_journaled(self, problem: str) -> Outcome:
        """The same decision, marked as not on record because the journal could not write."""
        if self.journal_problem is not None:
            return self
        return replace(
            self, message=f"{self.message} (not journaled: {problem})", journal_problem=problem
        )


@dataclass(frozen=True, slots=True)
class AuditNote:
    """Who sent a command, for the audit row the recorder commits with its event.

    `label` turns the worker's outcome into the row's outcome as the sender was
    answered ("accepted", "refused (409)"): the API knows its status codes, the
    core does not.
    """

    principal: str
    address: str
    action: str  # method and path, e.g. "POST /start"
    label: Callable[[Outcome], str]


@dataclass(frozen=True, slots=True)
class NoPayload:
    """Events that carry nothing: readiness, pause, resume, cancel, reset."""

    def as_dict(self) -> dict[str, Any]:
        return {}


@dataclass(frozen=True, slots=True)
class StartPayload:
    """START_REQUESTED: find the part on the table, or spray a named library part."""

    contour_matching: bool = True
    workpiece_id: str | None = None
    # The production order this run makes a part for (server/orders/): set by the cell,
    # never by the request, and kept in the run's params so the run's end finds its order.
    order_id: str | None = None

    def as_dict(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "contour_matching": self.contour_matching,
            "workpiece_id": self.workpiece_id,
        }
        if self.order_id is not None:
            data["order_id"] = self.order_id
        return data


@dataclass(frozen=True, slots=True)
class CreateWorkpiecePayload:
    """CREATE_WORKPIECE_REQUESTED: the name, id and spray settings of the new part."""

    name: str | None = None
    workpiece_id: str | None = None
    spray: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        fields = {"name": self.name, "workpiece_id": self.workpiece_id, "spray": self.spray}
        return {key: value for key, value in fields.items() if value is not None}


@dataclass(frozen=True, slots=True)
class JogPayload:
    """JOG_REQUESTED: one step of `distance_mm` along `axis` ("x", "y" or "z"), robot frame.

    A relative step, not a target: the target is the pose the worker reads when it
    decides, so a step can never be taken from a stale position.
    """

    axis: str = "z"
    distance_mm: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"axis": self.axis, "distance_mm": self.distance_mm}


@dataclass(frozen=True, slots=True)
class StopPayload:
    """EMERGENCY_STOP: why the stop was pressed, for the record."""

    reason: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"reason": self.reason} if self.reason else {}


@dataclass(frozen=True, slots=True)
class FaultPayload:
    """ERROR_OCCURRED: a device (or the system) reports a fault."""

    code: str
    message: str
    component: str

    def as_dict(self) -> dict[str, Any]:
        return {"code": self.code, "message": self.message, "component": self.component}


@dataclass(frozen=True, slots=True)
class RunCompletedPayload:
    """OPERATION_COMPLETED: the run that ended and what it returned."""

    run_id: str
    result: OperationResult = field(default_factory=OperationResult)

    def as_dict(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "result": self.result.as_dict()}


@dataclass(frozen=True, slots=True)
class RunFailedPayload:
    """OPERATION_FAILED: the run that failed, and the fault that ended it."""

    run_id: str
    code: str
    message: str
    component: str
    # The stack of the exception that ended the run: kept on the fault's row, not in the
    # event's data (every event is journaled; a stack belongs to the one fault).
    trace: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "code": self.code,
            "message": self.message,
            "component": self.component,
        }


Payload = (
    NoPayload
    | StartPayload
    | CreateWorkpiecePayload
    | JogPayload
    | StopPayload
    | FaultPayload
    | RunCompletedPayload
    | RunFailedPayload
)

PAYLOAD_OF_EVENT: Final = MappingProxyType(
    {
        **{event: NoPayload for event in Event},
        Event.START_REQUESTED: StartPayload,
        Event.CREATE_WORKPIECE_REQUESTED: CreateWorkpiecePayload,
        Event.JOG_REQUESTED: JogPayload,
        Event.EMERGENCY_STOP: StopPayload,
        Event.ERROR_OCCURRED: FaultPayload,
        Event.OPERATION_COMPLETED: RunCompletedPayload,
        Event.OPERATION_FAILED: RunFailedPayload,
    }
)


def payload_of(event: Event, payload: Payload | None) -> Payload:
    """`payload`, or the event's default one; refuses a payload of the wrong kind.

    A wrong kind is a programming error, not bad input: HTTP input is
    validated into its payload before it gets here.
    """
    expected: Callable[..., Payload] = PAYLOAD_OF_EVENT[event]
    if payload is None:
        return expected()  # a payload with required fields raises TypeError naming them
    if type(payload) is not expected:
        wanted = PAYLOAD_OF_EVENT[event].__name__
        raise TypeError(f"{event.value} carries {wanted}, not {type(payload).__name__}")
    return payload

"""What the machine remembers: the current state, the running operation, the
last error, a bounded transition history and processing statistics.

Only the worker writes here; everything else reads snapshots.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from server.core.machine.events import FaultPayload, Payload, RunFailedPayload, StopPayload
from server.core.machine.faults import classify, recommended_action
from server.core.machine.transitions import State

# The transports an event's `source` may begin with ("api:<token name>", "mqtt:<name>").
SOURCE_TRANSPORTS = frozenset({"api", "mqtt", "opcua"})


@dataclass(slots=True)
class TransitionRecord:
    """One entry of the transition history."""

    timestamp: float
    old_state: str
    new_state: str
    event: str
    event_id: str
    time_in_old_state: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "timestamp": self.timestamp,
            "old_state": self.old_state,
            "new_state": self.new_state,
            "event": self.event,
            "event_id": self.event_id,
            "time_in_old_state": self.time_in_old_state,
        }


@dataclass(slots=True)
class RunningOperation:
    """The operation the cell is doing now."""

    name: str
    run_id: str
    started_at: float
    params: dict[str, Any] = field(default_factory=dict)
    progress: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "run_id": self.run_id,
            "started_at": self.started_at,
            "params": self.params,
            "progress": self.progress or None,
        }

    def fault_context(self) -> dict[str, Any]:
        """What was going on when a fault came: the operation, its run, its parameters,
        the workpiece it was on and how far it had got."""
        context: dict[str, Any] = {"operation": self.name, "run_id": self.run_id}
        context.update(self.params)
        if "workpiece_id" in self.progress:
            context["workpiece_id"] = self.progress["workpiece_id"]
        if "waypoint" in self.progress:
            total = self.progress.get("total", "?")
            context["waypoint"] = f"{self.progress['waypoint']} of {total}"
        return context


def sender_of(source: str) -> str:
    """Who an event's `source` names, without its transport: `api:line 3 HMI` → `line 3 HMI`.

    A stop reason is read by people at the panel; the transport stays in the fault's
    `component`.
    """
    transport, sep, name = source.partition(":")
    return name if sep and transport in SOURCE_TRANSPORTS and name else source


@dataclass(slots=True)
class FaultRecord:
    """The fault that put (or keeps) the cell in ERROR."""

    code: str
    message: str
    component: str
    event_id: str
    time: float
    classification: str = "critical"
    recommended_action: str = ""
    # What the fault interrupted: {"operation": None} when no operation ran, else the
    # operation, its run id, parameters, workpiece and waypoint (fault_context).
    context: dict[str, Any] = field(default_factory=lambda: {"operation": None})
    trace: str = ""  # the stack, when an exception caused the fault

    @classmethod
    def of(
        cls,
        payload: Payload,
        source: str,
        event_id: str,
        at: float,
        interrupted: RunningOperation | None = None,
    ) -> FaultRecord:
        """The fault an event into ERROR reports: an e-stop, a device fault or a failed run,
        with the operation it interrupted (`interrupted`, None when none ran)."""
        trace = ""
        if isinstance(payload, FaultPayload | RunFailedPayload):
            code, message, component = payload.code, payload.message, payload.component
            if isinstance(payload, RunFailedPayload):
                trace = payload.trace
        else:  # the e-stop: who pressed it and why
            code, component = "EMERGENCY_STOP", source
            message = f"emergency stop by {sender_of(source)}"
            if isinstance(payload, StopPayload) and payload.reason:
                message += f": {payload.reason}"
        context = interrupted.fault_context() if interrupted else {"operation": None}
        return cls(
            code,
            message,
            component,
            event_id,
            at,
            classify(code),
            recommended_action(code),
            context,
            trace,
        )

    def as_dict(self) -> dict[str, Any]:
        # Spelled out: dataclasses.asdict deep-copies, and this runs on every
        # state change while a fault is on record.
        return {
            "code": self.code,
            "message": self.message,
            "component": self.component,
            "event_id": self.event_id,
            "time": self.time,
            "classification": self.classification,
            "recommended_action": self.recommended_action,
        }


class ProcessingStats:
    """Events processed and refused, and processing-time figures over a bounded window."""

    def __init__(self, window: int) -> None:
        self.processed = 0
        self.refused = 0
        self._durations: deque[float] = deque(maxlen=window)
        self.listeners: list[Callable[[float], None]] = []  # e.g. a metrics histogram

    def record(self, seconds: float, *, accepted: bool) -> None:
        self.processed += 1
        if not accepted:
            self.refused += 1
        self._durations.append(seconds)
        for listener in self.listeners:
            listener(seconds)

    def snapshot(self, queue_size: int) -> dict[str, Any]:
        durations = sorted(self._durations)
        average = sum(durations) / len(durations) if durations else 0.0
        p99 = (
            durations[min(len(durations) - 1, math.ceil(0.99 * len(durations)) - 1)]
            if durations
            else 0.0
        )
        return {
            "events_processed": self.processed,
            "events_refused": self.refused,
            "average_processing_time_ms": round(average * 1000, 4),
            "p99_processing_time_ms": round(p99 * 1000, 4),
            "queue_size": queue_size,
        }


@dataclass
class MachineContext:
    """The specification's StateMachineContext, plus what the HMI needs to show."""

    history_size: int
    state: State = State.INITIALIZING
    previous_state: State | None = None
    since: float = field(default_factory=time.time)
    operation: RunningOperation | None = None
    operation_data: dict[str, Any] = field(default_factory=dict)
    operation_result: dict[str, Any] | None = None
    error: FaultRecord | None = None
    stop_reason: FaultRecord | None = None  # first-out: the first fault since the last reset
    history: deque[TransitionRecord] = field(init=False)

    def __post_init__(self) -> None:
        self.history = deque(maxlen=self.history_size)

    @property
    def error_message(self) -> str | None:
        return self.error.message if self.error else None

    def enter(self, state: State, event: str, event_id: str, now: float) -> TransitionRecord:
        """Change to `state` on `event`; the transition goes into the bounded history.

        The states' names by `str()`, which is a StrEnum's value without the enum's
        Python-level `value` property (every change of state reads them)."""
        record = TransitionRecord(
            timestamp=now,
            old_state=str(self.state),
            new_state=str(state),
            event=event,
            event_id=event_id,
            time_in_old_state=round(now - self.since, 6),
        )
        self.history.append(record)
        self.previous_state, self.state, self.since = self.state, state, now
        return record

    def record_error(self, error: FaultRecord) -> None:
        """Note a fault; the first since the last reset stays the stop reason."""
        self.error = error
        if self.stop_reason is None:
            self.stop_reason = error

    def clear_error(self) -> None:
        self.error = None
        self.stop_reason = None

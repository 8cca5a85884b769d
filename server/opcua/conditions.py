"""The cell's alarms as OPC UA conditions: what is active, acknowledged, confirmed. Pure.

Each fault and each warning the cell raises on its bus is one condition, named by its
code (one condition per code: a code raised again while it is on record is the same
condition raised again, with the new message, waiting for a new acknowledgement).

- A fault (an `error` bus message: an e-stop, a device fault, a failed run, a halt a
  device did not confirm) stopped the cell. It stays active until the cell's stop
  reason is cleared, which only a reset back to IDLE does; the first fault since the
  last clear is the first-out (OPC UA's FirstInGroupFlag), as the cell's stop reason is.
- A warning (an `alert` bus message) is active while it is still true as far as the
  cell can tell: one whose cause the cell sees go away, until the cell says so with an
  `alert_cleared` message naming its code (the care meter's: a maintenance item done, a
  refill, glue dispensed again; the self-watch's: memory or free space back under their
  thresholds); one raised by a run (a calibration degrading, a slow operation) until a
  later run in the same state completes without raising it again; one raised in ERROR
  (the cell held in ERROR too long) until the cell leaves ERROR; one found at start (the
  journal found damaged) for as long as the server runs, as /health shows it.

Acknowledge and Confirm follow OPC 10000-9: a raise is unacknowledged (AckedState
false) with nothing to confirm (ConfirmedState true); Acknowledge makes it acked and
unconfirmed; Confirm confirms it. Each is refused for an EventId that is not the
condition's latest (the client acted on an old notice) or a branch already in that
state. Retain is true while the condition is active or unacknowledged, so a client's
alarm list keeps a cleared alarm nobody has seen yet, and drops it once acknowledged.

Every change returns the `Notice` to emit: the condition as it is now, with a fresh
EventId the book remembers for the next Acknowledge or Confirm.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from enum import Enum
from typing import Any, Final, Literal

Kind = Literal["fault", "warning"]

# OPC UA Severity (1..1000): the e-stop highest; a fault that stopped the cell high; a
# recoverable fault (retried, a part not found) lower; a warning (the cell runs on) below.
SEVERITY: Final = {"EMERGENCY_STOP": 1000, "critical": 800, "recoverable": 600, "warning": 400}


class ConditionClass(Enum):
    """OPC UA's condition classes the cell's alarms belong to (ConditionClassId)."""

    SAFETY = "safety"  # the e-stop
    PROCESS = "process"  # a fault that stopped the work
    MAINTENANCE = "maintenance"  # a warning: something to look after before it stops the cell


class Refused(Enum):
    """Why an Acknowledge or Confirm is refused (each an OPC UA status code)."""

    UNKNOWN_CONDITION = "BadNodeIdUnknown"
    EVENT_ID_UNKNOWN = "BadEventIdUnknown"
    ALREADY_ACKED = "BadConditionBranchAlreadyAcked"
    ALREADY_CONFIRMED = "BadConditionBranchAlreadyConfirmed"


@dataclass(frozen=True, slots=True)
class Condition:
    """One alarm as it is now."""

    code: str
    kind: Kind
    message: str
    component: str
    severity: int
    condition_class: ConditionClass
    raised_at: float  # when the cell raised it (Unix seconds): the event's Time
    changed_at: float  # when its active, acked or confirmed state last changed
    origin: str  # the cell state it was raised in
    raised_seq: int  # the bus message that raised it
    active: bool = True
    acked: bool = False
    confirmed: bool = True
    first_out: bool = False
    comment: str = ""
    user: str = ""  # who acknowledged or confirmed it last
    event_id: bytes = b""  # the EventId of its latest notice

    @property
    def retain(self) -> bool:
        """Whether a client keeps it in its alarm list (OPC UA's Retain)."""
        return self.active or not self.acked


@dataclass(frozen=True, slots=True)
class Notice:
    """A condition's change to emit as an OPC UA event, and what changed it."""

    condition: Condition
    why: str  # raised, cleared, acknowledged, confirmed


def severity_of(code: str, classification: str) -> int:
    return SEVERITY.get(code) or SEVERITY.get(classification) or SEVERITY["critical"]


def class_of(code: str, kind: Kind) -> ConditionClass:
    if code == "EMERGENCY_STOP":
        return ConditionClass.SAFETY
    return ConditionClass.MAINTENANCE if kind == "warning" else ConditionClass.PROCESS


class ConditionBook:
    """The conditions of one cell, changed by its bus messages and by clients' methods."""

    def __init__(self, event_ids: Iterable[bytes] | None = None) -> None:
        self.conditions: dict[str, Condition] = {}
        self._ids = iter(event_ids) if event_ids is not None else _counter()
        self._entered: dict[str, int] = {}  # each state's latest entry (bus seq)
        self._first_out_given = False

    def _notice(self, condition: Condition, why: str) -> Notice:
        condition = replace(condition, event_id=next(self._ids))
        self.conditions[condition.code] = condition
        return Notice(condition, why)

    # --- what the cell says -----------------------------------------------------------

    def on_message(self, kind: str, data: Mapping[str, Any], seq: int, at: float) -> list[Notice]:
        """The notices a bus message (`error`, `alert`, `alert_cleared` or `state_changed`)
        causes."""
        if kind == "error":
            return [self._raise("fault", data, seq, at)]
        if kind == "alert":
            return [self._raise("warning", data, seq, at)]
        if kind == "alert_cleared":
            return self._clear_warning(str(data.get("code") or ""), at)
        if kind == "state_changed":
            return self._on_transition(data, seq, at)
        return []

    def _clear_warning(self, code: str, at: float) -> list[Notice]:
        """The cell says a warning's cause has gone: that warning, if active, clears."""
        condition = self.conditions.get(code)
        if condition is None or condition.kind != "warning" or not condition.active:
            return []
        return [self._notice(replace(condition, active=False, changed_at=at), "cleared")]

    def _raise(self, kind: Kind, data: Mapping[str, Any], seq: int, at: float) -> Notice:
        code = str(data.get("code") or "UNKNOWN")
        classification = str(
            data.get("classification") or ("warning" if kind == "warning" else "critical")
        )
        # A fault the cell recorded (it has an event id) and the first since the last
        # clear is the first-out; a halt a device did not confirm is part of a stop, never
        # its reason.
        first_out = kind == "fault" and bool(data.get("event_id")) and not self._first_out_given
        if first_out:
            self._first_out_given = True
        raised_at = float(data.get("time") or at)
        condition = Condition(
            code=code,
            kind=kind,
            message=str(data.get("message") or code),
            component=str(data.get("component") or ""),
            severity=severity_of(code, classification),
            condition_class=class_of(code, kind),
            raised_at=raised_at,
            changed_at=at,
            origin=str(data.get("state") or ""),
            raised_seq=seq,
            first_out=first_out,
        )
        return self._notice(condition, "raised")

    def _on_transition(self, data: Mapping[str, Any], seq: int, at: float) -> list[Notice]:
        old, new, event = data.get("old_state"), data.get("new_state"), data.get("event")
        snapshot = data.get("snapshot") or {}
        ended: list[Condition] = []
        if not snapshot.get("stop_reason"):
            # The stop reason is cleared (a reset back to IDLE): every fault with it.
            ended += [c for c in self.conditions.values() if c.kind == "fault" and c.active]
            self._first_out_given = False
        if event == "OPERATION_COMPLETED" and isinstance(old, str):
            # A run completed without raising again what an earlier run in its state raised.
            began = self._entered.get(old, -1)
            ended += [
                c
                for c in self.conditions.values()
                if c.kind == "warning" and c.active and c.origin == old and c.raised_seq < began
            ]
        if old == "ERROR" and new != "ERROR":
            ended += [
                c
                for c in self.conditions.values()
                if c.kind == "warning" and c.active and c.origin == "ERROR"
            ]
        if isinstance(new, str):
            self._entered[new] = seq
        notices = []
        for condition in {c.code: c for c in ended}.values():
            notices.append(self._notice(replace(condition, active=False, changed_at=at), "cleared"))
        return notices

    def clear_all_faults(self, at: float) -> list[Notice]:
        """The cell has no stop reason (found when catching up): its faults are cleared."""
        self._first_out_given = False
        return [
            self._notice(replace(c, active=False, changed_at=at), "cleared")
            for c in list(self.conditions.values())
            if c.kind == "fault" and c.active
        ]

    # --- what a client asks -----------------------------------------------------------

    def acknowledge(
        self, code: str, event_id: bytes, comment: str, user: str, at: float
    ) -> Notice | Refused:
        """Acknowledge the condition's latest notice; it then waits for a Confirm."""
        condition = self._current(code, event_id)
        if isinstance(condition, Refused):
            return condition
        if condition.acked:
            return Refused.ALREADY_ACKED
        changed = replace(
            condition, acked=True, confirmed=False, comment=comment, user=user, changed_at=at
        )
        return self._notice(changed, "acknowledged")

    def confirm(
        self, code: str, event_id: bytes, comment: str, user: str, at: float
    ) -> Notice | Refused:
        """Confirm an acknowledged condition (the cause is dealt with)."""
        condition = self._current(code, event_id)
        if isinstance(condition, Refused):
            return condition
        if condition.confirmed:
            return Refused.ALREADY_CONFIRMED
        changed = replace(condition, confirmed=True, comment=comment, user=user, changed_at=at)
        return self._notice(changed, "confirmed")

    def check(self, method: str, code: str, event_id: bytes) -> Refused | None:
        """Why `method` (Acknowledge or Confirm) would be refused now; None if it would not."""
        condition = self._current(code, event_id)
        if isinstance(condition, Refused):
            return condition
        if method == "Acknowledge" and condition.acked:
            return Refused.ALREADY_ACKED
        if method == "Confirm" and condition.confirmed:
            return Refused.ALREADY_CONFIRMED
        return None

    def _current(self, code: str, event_id: bytes) -> Condition | Refused:
        condition = self.conditions.get(code)
        if condition is None:
            return Refused.UNKNOWN_CONDITION
        if event_id != condition.event_id:
            return Refused.EVENT_ID_UNKNOWN
        return condition

    def retained(self) -> list[Condition]:
        """The conditions a client's ConditionRefresh is sent (Retain true)."""
        return [c for c in self.conditions.values() if c.retain]


def _counter() -> Iterator[bytes]:
    """Event ids unique within the process: a prefix per book and a count."""
    prefix = os.urandom(8).hex()
    return (f"{prefix}-{n}".encode() for n in itertools.count(1))

"""The whole decision on one event, as one pure function: `decide(state, event, payload, facts)`.

Theory of operation
-------------------
The table (`transitions.py`) says where an event may lead, the engine (`engine.py`)
checks a row's guard, and the actions (`actions.py`) say what the row does. This
module adds every other rule that decides whether an event is accepted, so the
worker only executes what it is given. In the order they are asked:

1. **Late completions.** OPERATION_COMPLETED or OPERATION_FAILED of a run that is
   no longer the current one (it was cancelled or stopped meanwhile) is ignored:
   refused, nothing changes.
2. **The journal cannot write.** A person's command (the e-stop excepted) queued
   before the journal's last write failed is refused: nothing is decided that
   could not be put on record. The e-stop stops the cell whatever the disk says.
3. **The reset's two passes.** A reset in ERROR is first sent to probe every
   device live (`ProbeDevices`), and the worker goes on deciding other events
   meanwhile; one reset probes at a time. When it comes back, an e-stop or a
   fault decided since the probe began overtakes it (refused); otherwise the
   probe's findings are the FAULTS_CLEARED guard's facts.
4. **The table and its guards** (`engine.step`).
5. **The active order.** While a production order is active, a start of its
   workpiece (or of none named) is one of its parts: its payload is rewritten to
   name the order, whatever state the start is then decided in. A start naming
   another workpiece is refused. Decided here and nowhere else.
6. **Preconditions**: what a command needs besides the right state (a named,
   existing part; a calibration; a jog step within its limit; a safe position
   inside the workspace). A run that cannot succeed, once accepted, would fail
   inside the operation and drive the cell into ERROR for an operator's typo, so
   what can be checked before the transition is checked before it: the command
   is refused, the state does not change. A refusal with a `field` is the
   request's fault (HTTP 422 naming the field), without one the cell's (HTTP 409
   saying what to do first). The operations check again when they run.
7. **Overtaken by a stop.** An accepted decision that does not itself lead to
   ERROR carries a checkpoint: the index of its first action after the exit
   actions. Before running it the worker asks `Accepted.overtaken` whether an
   e-stop was requested since the decision was made; if so the decision is
   abandoned (nothing decided before a stop may undo it).
8. **Asked before a stop.** A command carries the e-stops counted when it reached
   its door (`Facts.asked_at_estops`); one made since, ahead of it, refuses it
   whatever the state, so nothing sent before a stop is decided after it (a reset
   pressed just before an e-stop never clears that stop's ERROR). Its sender may
   send it again.

`Facts` is everything the worker knows that these rules read, gathered before
each decision (`server/core/worker/facts.py`). No I/O, no clock, no loop here, so
the property tests (`tests/unit/test_decide.py`) run the whole decision over
arbitrary states, events, payloads and facts.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Final

from server.common.errors import TransitionNotAllowed
from server.core.machine.actions import EXIT_ACTIONS, actions_of
from server.core.machine.engine import Decision, step
from server.core.machine.engine import Facts as GuardFacts
from server.core.machine.events import (
    CreateWorkpiecePayload,
    JogPayload,
    Payload,
    StartPayload,
)
from server.core.machine.transitions import (
    COMMANDS,
    TRANSITIONS,
    Event,
    State,
    Transition,
    event_label,
)
from server.core.operations.jog import step_problem
from server.core.operations.safe_position import workspace_problem
from server.drivers.base import Pose
from server.settings.motion import MotionSettings

COMPLETION_EVENTS: Final = frozenset({Event.OPERATION_COMPLETED, Event.OPERATION_FAILED})
# A person's commands, each answered only once on record: refused while the journal cannot
# write. The e-stop is not among them: it stops the cell whatever the disk says.
JOURNALED_COMMANDS: Final = frozenset(COMMANDS.values()) - {Event.EMERGENCY_STOP}
OVERTAKEN: Final = "overtaken by an emergency stop while it was being decided; nothing was changed"
RESET_OVERTAKEN: Final = (
    "overtaken by an emergency stop or a fault while the devices were probed; "
    "still in ERROR, nothing was changed: reset again"
)
RESET_UNDER_WAY: Final = "a reset is already probing the devices; wait for its answer"
ASKED_BEFORE_STOP: Final = (
    "sent before an emergency stop that was made first; nothing was changed "
    "(send it again if it is still wanted)"
)


@dataclass(frozen=True, slots=True)
class Stops:
    """How many e-stops were requested and faults recorded so far (counters, never reset)."""

    estops: int = 0
    faults: int = 0


@dataclass(frozen=True, slots=True)
class Probed:
    """A reset back from its live probe: the stops counted when it began, and what it found."""

    began: Stops
    found: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class ActiveOrder:
    """The production order the cell works through: a start makes parts of it."""

    order_id: str
    workpiece_id: str


@dataclass(frozen=True, slots=True)
class Library:
    """What a start or a create-workpiece needs of the library and the calibrations.

    `known` holds those of the workpieces the event may name (its own, the active
    order's) that the library has; `calibration_problem` is why the image-to-robot
    map cannot be used for this event's purpose, if it cannot.
    """

    known: frozenset[str] = frozenset()
    empty: bool = False
    calibration_problem: str | None = None


NO_LIBRARY: Final = Library()  # what an event that names no part knows of the library
NO_STOPS: Final = Stops()
NO_GUARD_FACTS: Final = GuardFacts()


@dataclass(slots=True)
class Facts:
    """What the worker knows when it decides one event.

    Not frozen, because the worker builds one for every event it decides and a frozen
    dataclass's constructor costs several times a plain one's (and sets `library` and
    `glue_line_problem` only for the events that read them); nothing changes a `Facts`
    once gathered (every field holds an immutable value), and `decide` reads it only.
    """

    guards: GuardFacts = NO_GUARD_FACTS  # ready devices, known faults
    journal_problem: str | None = None  # why the journal's last write failed, while it fails
    current_run: str | None = None  # the run id of the operation under way
    stops: Stops = NO_STOPS
    probing: bool = False  # a reset's probe of the devices is under way
    probed: Probed | None = None  # set when this event is that reset, back from its probe
    active_order: ActiveOrder | None = None
    library: Library = NO_LIBRARY
    glue_line_problem: str | None = None  # why a start must wait for a purge (pot life)
    # The e-stops counted when the command reached its door (None: not a command)
    asked_at_estops: int | None = None


@dataclass(frozen=True, slots=True)
class Refusal:
    """The event is refused and nothing changes; `field` names a wrong request field.

    `payload` is the event's payload as decided (a start claimed for the active
    order names it), which the journal records with the refusal.
    """

    message: str
    field: str | None = None
    journal_problem: str | None = None
    payload: Payload | None = None


@dataclass(frozen=True, slots=True)
class ProbeDevices:
    """A reset's first pass: probe every device live, then decide the reset again."""

    began: Stops


@dataclass(slots=True)
class Accepted:
    """The event is accepted: run `decision.actions` in order with `payload`.

    Not frozen, for `Facts`' reason: one is built for every event accepted, and nothing
    changes it once built.

    `checkpoint` is the index of the first action after the exit actions, for a
    decision that does not lead to ERROR: before it, `overtaken` is asked with the
    e-stops requested by then. None when there is nothing to abandon.
    """

    decision: Decision
    payload: Payload
    checkpoint: int | None
    estops: int  # e-stops requested when decided (for a reset: when its probe began)

    def overtaken(self, estops_now: int) -> Refusal | None:
        """The refusal when an e-stop was requested after this decision was made."""
        return Refusal(OVERTAKEN) if estops_now != self.estops else None


Verdict = Accepted | Refusal | ProbeDevices


def decide(
    state: State, event: Event, payload: Payload, facts: Facts, settings: MotionSettings
) -> Verdict:
    """Decide `event` with `payload` in `state` (see the module's theory of operation)."""
    if facts.active_order is None or event is not Event.START_REQUESTED:
        return _decide(state, event, payload, facts, settings)  # nothing to claim
    claimed = claim_for_order(event, payload, facts.active_order)
    verdict = _decide(state, event, claimed, facts, settings)
    if claimed is not payload and isinstance(verdict, Refusal):
        return replace(verdict, payload=claimed)
    return verdict


def claim_for_order(event: Event, payload: Payload, order: ActiveOrder | None) -> Payload:
    """A start of the active order's workpiece (or of none named) as a part of that order."""
    if (
        event is not Event.START_REQUESTED
        or order is None
        or not isinstance(payload, StartPayload)
        or payload.order_id is not None  # the order's own start
        or payload.workpiece_id not in (None, order.workpiece_id)  # refused below
    ):
        return payload
    return StartPayload(payload.contour_matching, order.workpiece_id, order.order_id)


def _decide(
    state: State, event: Event, payload: Payload, facts: Facts, settings: MotionSettings
) -> Verdict:
    if event in COMPLETION_EVENTS:
        run_id = getattr(payload, "run_id", None)
        if run_id is None or run_id != facts.current_run:
            return Refusal(f"{event.value} of a run that already ended; ignored")
    if facts.journal_problem is not None and event in JOURNALED_COMMANDS:
        problem = facts.journal_problem  # queued before the journal failed: decide nothing
        return Refusal(f"refused: the journal cannot write ({problem})", journal_problem=problem)
    guards, estops = facts.guards, facts.stops.estops
    asked_at = facts.asked_at_estops
    if asked_at not in (None, estops) and event in JOURNALED_COMMANDS and facts.probed is None:
        return Refusal(ASKED_BEFORE_STOP)  # (a reset back from its probe: its own rule)
    if facts.probed is not None and event is Event.RESET_REQUESTED:  # back from its probe
        if facts.stops != facts.probed.began:
            return Refusal(RESET_OVERTAKEN)
        guards = GuardFacts(ready_devices=guards.ready_devices, active_faults=facts.probed.found)
        estops = facts.probed.began.estops
    elif event is Event.RESET_REQUESTED and state is State.ERROR:
        return Refusal(RESET_UNDER_WAY) if facts.probing else ProbeDevices(facts.stops)
    try:
        decision = step(state, event, guards)
    except TransitionNotAllowed as refusal:
        return Refusal(str(refusal))
    unmet = precondition(event, payload, facts, settings)
    if unmet is not None:
        return unmet
    return Accepted(decision, payload, _CHECKPOINTS[state][event], estops)


def _checkpoint(row: Transition) -> int | None:
    """Index of the row's first action after its exit actions; None into ERROR (where a
    stop leads, so it is never overtaken) or when there is none."""
    if row.target is State.ERROR:
        return None
    actions = enumerate(actions_of(row))
    return next((i for i, action in actions if action not in EXIT_ACTIONS), None)


# Each row's checkpoint by state and event, worked out once at import: every accepted
# event reads it, and two lookups by enum (a string's cached hash) cost less than
# hashing the row's fields or working it out again.
_CHECKPOINTS: Final = {
    state: {event: _checkpoint(row) for event, row in rows.items()}
    for state, rows in TRANSITIONS.items()
}


def precondition(
    event: Event, payload: Payload, facts: Facts, settings: MotionSettings
) -> Refusal | None:
    """Why `event` with `payload` cannot be accepted now besides its state, or None."""
    if isinstance(payload, StartPayload):
        return _start(payload, facts) or _glue_line(facts)
    if isinstance(payload, CreateWorkpiecePayload):
        return _create_workpiece(payload, facts.library)
    if isinstance(payload, JogPayload):
        wrong = step_problem(payload.axis, payload.distance_mm, settings)
        return Refusal(wrong[1], field=wrong[0]) if wrong is not None else None
    if event is Event.HOME_REQUESTED:  # checked at load too; again before anything moves
        problem = workspace_problem(Pose.from_sequence(settings.safe_position), settings)
        if problem is not None:
            return Refusal(
                f"the safe position is outside the workspace ({problem}): correct "
                "safe_position or the workspace bounds in the settings"
            )
    return None


def _start(start: StartPayload, facts: Facts) -> Refusal | None:
    order, library = facts.active_order, facts.library
    if order is not None and start.workpiece_id not in (None, order.workpiece_id):
        return Refusal(
            f"order {order.order_id} is active and makes {order.workpiece_id!r}: close "
            "it first to spray another workpiece (this start: workpiece_id "
            f"{start.workpiece_id!r})"
        )
    if not start.contour_matching and not start.workpiece_id:
        return Refusal(
            "workpiece_id is required when contour_matching is false: name the library "
            "part to spray (GET /workpieces lists them)",
            field="workpiece_id",
        )
    if start.workpiece_id and start.workpiece_id not in library.known:
        return Refusal(
            f"workpiece {start.workpiece_id!r} is not in the library: GET /workpieces "
            "lists the parts, create-workpiece adds one"
        )
    if start.contour_matching:
        if library.empty:
            return Refusal(
                "the workpiece library is empty: run create-workpiece with a part on the "
                "table first"
            )
        if library.calibration_problem is not None:
            return Refusal(library.calibration_problem)
    return None


def _glue_line(facts: Facts) -> Refusal | None:
    problem = facts.glue_line_problem
    return Refusal(f"{problem} (maintenance: POST /purge)") if problem is not None else None


def _create_workpiece(create: CreateWorkpiecePayload, library: Library) -> Refusal | None:
    if create.workpiece_id and create.workpiece_id in library.known:
        return Refusal(
            f"workpiece {create.workpiece_id!r} already exists and create-workpiece never "
            f"replaces a part: change it with PUT /workpieces/{create.workpiece_id} "
            "(maintenance), or choose another workpiece_id"
        )
    if library.calibration_problem is not None:
        return Refusal(library.calibration_problem)
    return None


@functools.cache
def accepted_message(state: State, event: Event, target: State) -> str:
    """The answer to an accepted event that led from `state` to `target` (one per row of
    the table: built once, not for every event accepted)."""
    return f"{event_label(event)} accepted: {state.value} → {target.value}"

"""The pure engine: given a state, an event and the facts, decide the next state.

No I/O, no clock, no loop: `step` is a function of its arguments, so it can be
tested exhaustively and reused by anything that needs to know what *would*
happen (the "allowed now?" query, the diagram, the property tests). Only the
worker acts on a decision.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Final

from server.common.errors import GuardRefused, TransitionNotAllowed
from server.core.machine.actions import Action, actions_of
from server.core.machine.transitions import (
    COMMANDS,
    TRANSITIONS,
    Event,
    Guard,
    State,
    Transition,
    event_label,
)

REQUIRED_DEVICES: frozenset[str] = frozenset({"robot", "camera", "glue"})


@dataclass(frozen=True, slots=True)
class Facts:
    """What the guards may look at, gathered by the worker before each step."""

    ready_devices: frozenset[str] = frozenset()
    active_faults: tuple[str, ...] = field(default_factory=tuple)


@dataclass(frozen=True, slots=True)
class Decision:
    """The outcome of one accepted event: the row it matched and what to do, in order."""

    event: Event
    transition: Transition
    actions: tuple[Action, ...]

    @property
    def source(self) -> State:
        return self.transition.source

    @property
    def target(self) -> State:
        return self.transition.target

    @property
    def changes_state(self) -> bool:
        return self.source is not self.target


def _guard_failure(guard: Guard | None, facts: Facts) -> str | None:
    """Why `guard` does not hold, or None when it does."""
    if guard is None:
        return None
    if guard is Guard.ALL_DEVICES_READY:
        missing = sorted(REQUIRED_DEVICES - facts.ready_devices)
        return f"waiting for {', '.join(missing)} to report ready" if missing else None
    if guard is Guard.FAULTS_CLEARED:
        if facts.active_faults:
            return "fault still active: " + "; ".join(facts.active_faults)
        return None
    raise AssertionError(f"unhandled guard {guard!r}")


def step(state: State, event: Event, facts: Facts | None = None) -> Decision:
    """Decide what `event` does in `state`.

    Raises TransitionNotAllowed when the table has no row for the pair, and
    GuardRefused (a subclass) when the row exists but its guard does not hold;
    in both cases the state is unchanged.
    """
    decision = DECISIONS[state].get(event)
    if decision is None:
        raise TransitionNotAllowed(
            event.value, state.value, f"{event_label(event)} is not allowed in {state.value}"
        )
    guard = decision.transition.guard
    if guard is not None:
        failure = _guard_failure(guard, facts or NO_FACTS)
        if failure is not None:
            raise GuardRefused(
                event.value,
                state.value,
                f"{event_label(event)} is refused in {state.value}: {failure}",
            )
    return decision


NO_FACTS: Final = Facts()
# Each row's decision, built once at import: a decision is the row and its actions
# alone (frozen), so every event accepted by a row gets the same one, and `step` pays
# neither a new Decision nor `actions_of`'s cache lookup, which hashes the row's
# fields, for each event.
DECISIONS: Final = MappingProxyType(
    {
        state: MappingProxyType(
            {event: Decision(event, row, actions_of(row)) for event, row in rows.items()}
        )
        for state, rows in TRANSITIONS.items()
    }
)


def check(state: State, event: Event, facts: Facts | None = None) -> tuple[bool, str]:
    """Whether `event` would be accepted now, with the reason when it would not."""
    try:
        decision = step(state, event, facts)
    except TransitionNotAllowed as refusal:
        return False, str(refusal)
    return True, f"{event_label(event)} is allowed in {state.value} (→ {decision.target.value})"


def available_commands(state: State, facts: Facts | None = None) -> list[str]:
    """The operator commands accepted in `state` right now (guards included)."""
    return list(_available(state, facts or Facts()))


@functools.lru_cache(maxsize=256)
def _available(state: State, facts: Facts) -> tuple[str, ...]:
    # Every GET /state and WebSocket snapshot asks; the answer depends on nothing else.
    rows = TRANSITIONS[state]
    return tuple(
        name
        for name, event in COMMANDS.items()
        if (row := rows.get(event)) is not None and _guard_failure(row.guard, facts) is None
    )

"""Properties of the whole decision (`server.core.machine.decide`), over arbitrary inputs.

Hypothesis draws a state, an event with a payload of its kind, and any facts
(ready devices, known faults, a journal that cannot write, the current run,
e-stops and faults counted, a reset's probe under way or back, an active
order, what the library holds), and checks the rules that hold for every
combination, not only the table's rows.
"""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.core.machine import decide
from server.core.machine.actions import EXIT_ACTIONS, Action
from server.core.machine.decide import (
    Accepted,
    ActiveOrder,
    Facts,
    Library,
    Probed,
    ProbeDevices,
    Refusal,
    Stops,
)
from server.core.machine.engine import Facts as GuardFacts
from server.core.machine.engine import step
from server.core.machine.events import (
    CreateWorkpiecePayload,
    FaultPayload,
    JogPayload,
    Payload,
    RunCompletedPayload,
    RunFailedPayload,
    StartPayload,
    StopPayload,
    payload_of,
)
from server.core.machine.transitions import TRANSITIONS, Event, State
from server.settings.model import Settings

pytestmark = pytest.mark.unit

SETTINGS = Settings()
PARTS = ("part-a", "part-b")
RUNS = ("run-1", "run-2")
ORDER = "ord-1"
FAULT_EVENTS = frozenset({Event.EMERGENCY_STOP, Event.ERROR_OCCURRED, Event.OPERATION_FAILED})

maybe_part = st.sampled_from((None, *PARTS))
payloads: dict[Event, st.SearchStrategy[Any]] = {
    Event.START_REQUESTED: st.builds(
        StartPayload, st.booleans(), maybe_part, st.sampled_from((None, ORDER))
    ),
    Event.CREATE_WORKPIECE_REQUESTED: st.builds(CreateWorkpiecePayload, workpiece_id=maybe_part),
    Event.JOG_REQUESTED: st.builds(
        JogPayload,
        st.sampled_from(("x", "y", "z", "w")),
        st.sampled_from((0.0, 1.0, -5.0, 1e6)),
    ),
    Event.EMERGENCY_STOP: st.builds(StopPayload, st.sampled_from((None, "test"))),
    Event.ERROR_OCCURRED: st.just(FaultPayload("TEST", "injected", "test")),
    Event.OPERATION_COMPLETED: st.builds(RunCompletedPayload, st.sampled_from(RUNS)),
    Event.OPERATION_FAILED: st.builds(
        RunFailedPayload, st.sampled_from(RUNS), st.just("TEST"), st.just("x"), st.just("test")
    ),
}


@st.composite
def events(draw: st.DrawFn) -> tuple[Event, Payload]:
    event = draw(st.sampled_from(Event))
    strategy = payloads.get(event)
    return event, draw(strategy) if strategy is not None else payload_of(event, None)


stops = st.builds(Stops, st.integers(0, 2), st.integers(0, 2))
facts_strategy = st.builds(
    Facts,
    guards=st.builds(
        GuardFacts,
        st.frozensets(st.sampled_from(("robot", "camera", "glue"))),
        st.lists(st.just("glue: low pressure"), max_size=1).map(tuple),
    ),
    journal_problem=st.sampled_from((None, "disk full")),
    current_run=st.sampled_from((None, *RUNS)),
    stops=stops,
    probing=st.booleans(),
    probed=st.none() | st.builds(Probed, stops, st.sampled_from(((), ("robot: no answer",)))),
    active_order=st.none() | st.builds(ActiveOrder, st.just(ORDER), st.sampled_from(PARTS)),
    asked_at_estops=st.none() | st.integers(0, 2),
    library=st.builds(
        Library,
        st.frozensets(st.sampled_from(PARTS)),
        st.booleans(),
        st.sampled_from((None, "contour matching needs the robot calibration")),
    ),
)
states = st.sampled_from(State)


def decided(state: State, event: Event, payload: Payload, facts: Facts) -> decide.Verdict:
    return decide.decide(state, event, payload, facts, SETTINGS)


def state_after(state: State, verdict: decide.Verdict) -> State:
    """The state the worker leaves the cell in when it executes `verdict` to the end."""
    return verdict.decision.target if isinstance(verdict, Accepted) else state


@settings(max_examples=250)
@given(states, events(), facts_strategy)
def test_the_decision_is_a_function_of_its_arguments(state, drawn, facts) -> None:
    event, payload = drawn
    assert decided(state, event, payload, facts) == decided(state, event, payload, facts)


@settings(max_examples=250)
@given(states, events(), facts_strategy)
def test_only_an_accepted_decision_changes_state_and_only_along_a_row(state, drawn, facts):
    event, payload = drawn
    verdict = decided(state, event, payload, facts)
    if not isinstance(verdict, Accepted):
        assert state_after(state, verdict) is state  # a refusal or a probe changes nothing
        return
    row = TRANSITIONS[state][event]
    assert verdict.decision.transition == row
    # A reset is decided on its probe's findings, not on the guards drawn (which may
    # hold a fault the probe no longer found: stepping on them would refuse).
    if event is not Event.RESET_REQUESTED:
        assert verdict.decision.actions == step(state, event, facts.guards).actions


@settings(max_examples=250)
@given(states, st.sampled_from(sorted(FAULT_EVENTS)), facts_strategy, st.data())
def test_every_fault_decision_closes_the_valve_first(state, event, facts, data) -> None:
    payload = data.draw(payloads[event])
    verdict = decided(state, event, payload, facts)
    if event is Event.OPERATION_FAILED and not isinstance(verdict, Accepted):
        return  # a late failure, or one where no operation runs: nothing to close
    assert isinstance(verdict, Accepted)
    actions = verdict.decision.actions
    if state is not State.ERROR:
        assert actions[0] is Action.HALT
    assert Action.RECORD_FAULT in actions
    assert verdict.decision.target is State.ERROR
    assert verdict.checkpoint is None  # never overtaken: it is where a stop leads


@settings(max_examples=250)
@given(states, st.sampled_from((Event.EMERGENCY_STOP, Event.ERROR_OCCURRED)), facts_strategy)
def test_a_stop_or_a_fault_is_never_refused(state, event, facts) -> None:
    payload = FaultPayload("TEST", "injected", "test") if event is Event.ERROR_OCCURRED else None
    verdict = decided(state, event, payload_of(event, payload), facts)
    assert isinstance(verdict, Accepted)
    assert verdict.decision.target is State.ERROR


@settings(max_examples=250)
@given(states, st.sampled_from((Event.OPERATION_COMPLETED, Event.OPERATION_FAILED)),
       facts_strategy, st.data())  # fmt: skip
def test_a_late_completion_never_changes_state(state, event, facts, data) -> None:
    payload = data.draw(payloads[event])
    verdict = decided(state, event, payload, facts)
    if payload.run_id != facts.current_run:
        assert isinstance(verdict, Refusal)
        assert "already ended" in verdict.message
        assert state_after(state, verdict) is state


@settings(max_examples=250)
@given(states, events(), facts_strategy)
def test_a_command_is_refused_while_the_journal_cannot_write(state, drawn, facts) -> None:
    event, payload = drawn
    verdict = decided(state, event, payload, facts)
    if facts.journal_problem is not None and event in decide.JOURNALED_COMMANDS:
        late = event in decide.COMPLETION_EVENTS
        assert isinstance(verdict, Refusal)
        assert late or verdict.journal_problem == facts.journal_problem


@settings(max_examples=250)
@given(states, st.data(), facts_strategy)
def test_a_start_during_an_active_order_is_a_part_of_it_or_refused(state, data, facts):
    start = data.draw(payloads[Event.START_REQUESTED])
    order = facts.active_order
    verdict = decided(state, Event.START_REQUESTED, start, facts)
    if order is None:
        assert not isinstance(verdict, Refusal) or verdict.payload is None  # never rewritten
        return
    other = start.workpiece_id not in (None, order.workpiece_id)
    claimed = StartPayload(start.contour_matching, order.workpiece_id, order.order_id)
    if isinstance(verdict, Accepted):
        assert not other
        # A person's start becomes the order's part; the order's own start stays as it is.
        assert verdict.payload == (claimed if start.order_id is None else start)
        return
    assert isinstance(verdict, Refusal)
    if other:
        assert verdict.payload is None  # refused as it was asked, never rewritten
    elif start.order_id is None:
        assert verdict.payload == claimed  # recorded as the part it would have been


@settings(max_examples=200)
@given(st.data(), facts_strategy)
def test_a_start_of_another_workpiece_is_refused_by_the_order_rule_alone(data, facts) -> None:
    start = data.draw(payloads[Event.START_REQUESTED])
    order = facts.active_order
    ready = Facts(active_order=order, library=Library(known=frozenset(PARTS)))
    verdict = decided(State.IDLE, Event.START_REQUESTED, start, ready)
    if order is not None and start.workpiece_id not in (None, order.workpiece_id):
        assert isinstance(verdict, Refusal)
        assert f"order {order.order_id} is active" in verdict.message
    elif start.contour_matching or start.workpiece_id or (order and start.order_id is None):
        assert isinstance(verdict, Accepted)


@settings(max_examples=250)
@given(events(), facts_strategy)
def test_a_reset_is_decided_in_two_passes(drawn, facts) -> None:
    probing = Facts(**{**_fields(facts), "probed": None})
    first = decided(State.ERROR, Event.RESET_REQUESTED, payload_of(Event.RESET_REQUESTED, None),
                    probing)  # fmt: skip
    if facts.journal_problem is not None:
        assert isinstance(first, Refusal)
    elif facts.asked_at_estops not in (None, facts.stops.estops):  # a stop came since
        assert first == Refusal(decide.ASKED_BEFORE_STOP)
    elif facts.probing:
        assert first == Refusal(decide.RESET_UNDER_WAY)
    else:
        assert first == ProbeDevices(facts.stops)
    if facts.probed is None or facts.journal_problem is not None:
        return
    second = decided(State.ERROR, Event.RESET_REQUESTED, payload_of(Event.RESET_REQUESTED, None),
                     facts)  # fmt: skip
    if facts.stops != facts.probed.began:
        assert second == Refusal(decide.RESET_OVERTAKEN)
    elif facts.probed.found:
        assert isinstance(second, Refusal) and "fault still active" in second.message
    else:
        assert isinstance(second, Accepted) and second.decision.target is State.IDLE
        assert second.estops == facts.probed.began.estops


@settings(max_examples=250)
@given(states, events(), facts_strategy)
def test_an_accepted_decision_is_abandoned_after_its_exit_actions_if_a_stop_came(
    state, drawn, facts
) -> None:
    event, payload = drawn
    verdict = decided(state, event, payload, facts)
    if not isinstance(verdict, Accepted):
        return
    actions, checkpoint = verdict.decision.actions, verdict.checkpoint
    if verdict.decision.target is State.ERROR:
        assert checkpoint is None
        return
    exits = [i for i, a in enumerate(actions) if a not in EXIT_ACTIONS]
    assert checkpoint == (exits[0] if exits else None)
    assert all(a in EXIT_ACTIONS for a in actions[: checkpoint or 0])
    assert verdict.overtaken(verdict.estops) is None
    assert verdict.overtaken(verdict.estops + 1) == Refusal(decide.OVERTAKEN)


def _fields(facts: Facts) -> dict[str, Any]:
    return {name: getattr(facts, name) for name in Facts.__slots__}


@settings(max_examples=250)
@given(states, events(), facts_strategy)
def test_a_command_asked_before_a_stop_made_since_is_refused_whatever_the_state(
    state, drawn, facts
) -> None:
    """Nothing sent before an e-stop is decided after it; a stop is never refused."""
    event, payload = drawn
    verdict = decided(state, event, payload, facts)
    asked_before = facts.asked_at_estops not in (None, facts.stops.estops)
    if event in decide.COMPLETION_EVENTS or facts.journal_problem is not None:
        return  # refused by their own rules first
    if asked_before and event in decide.JOURNALED_COMMANDS and facts.probed is None:
        # the payload as decided rides along (a start claimed for the active order)
        assert isinstance(verdict, Refusal), verdict
        assert (verdict.message, verdict.field) == (decide.ASKED_BEFORE_STOP, None)
    elif isinstance(verdict, Refusal):
        assert verdict.message != decide.ASKED_BEFORE_STOP

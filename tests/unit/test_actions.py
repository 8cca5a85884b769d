"""The safety order as a property of the table: every (state, event) pair, no event loop.

What a transition does is derived from its row (server/core/machine/actions.py), so
these checks cover every path the machine can take, not the few a scenario
test happens to drive.
"""

from __future__ import annotations

import itertools

import pytest

from server.common.errors import TransitionNotAllowed
from server.core.machine.actions import EXIT_ACTIONS, Action, actions_of, ends_operation
from server.core.machine.engine import REQUIRED_DEVICES, Facts, step
from server.core.machine.transitions import OPERATIONAL_STATES, Event, State, transitions

ALL_READY = Facts(ready_devices=REQUIRED_DEVICES)
PAIRS = list(itertools.product(State, Event))


def _decided(state: State, event: Event):
    try:
        return step(state, event, ALL_READY)
    except TransitionNotAllowed:
        return None


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_the_valve_closes_before_anything_else_into_error_or_out_of_an_operation(state, event):
    decision = _decided(state, event)
    if decision is None:
        return  # refused: the state is unchanged and nothing is done
    actions = decision.actions
    into_error = decision.target is State.ERROR and decision.changes_state
    if into_error or ends_operation(decision.transition):
        assert actions[0] is Action.HALT, f"{state} on {event}: {actions}"


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_a_run_is_halted_once_before_it_is_cancelled(state, event):
    """One HALT, before the cancellation: it cuts the run's leash first, so nothing the
    run still had on its way goes out after it (tests/integration/test_halt_frames.py)."""
    decision = _decided(state, event)
    if decision is None or Action.CANCEL_RUN not in decision.actions:
        return
    actions = list(decision.actions)
    cancelled = actions.index(Action.CANCEL_RUN)
    assert actions.count(Action.HALT) == 1 and actions.index(Action.HALT) < cancelled, actions
    assert actions.index(Action.RECORD_RUN_END) < cancelled  # its outcome before it is gone


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_exit_actions_come_before_the_change_and_the_fault_before_the_state(state, event):
    decision = _decided(state, event)
    if decision is None:
        return
    actions = list(decision.actions)
    kinds = [action in EXIT_ACTIONS for action in actions]
    assert kinds == sorted(kinds, reverse=True), f"exit actions not first: {actions}"
    for before in (Action.RECORD_FAULT, Action.ENTER_IDLE):  # what the new state's snapshot shows
        if before in actions and Action.CHANGE_STATE in actions:
            assert actions.index(before) < actions.index(Action.CHANGE_STATE)
    for entry in (Action.START_RUN, Action.START_HOMING):
        if entry in actions and Action.CHANGE_STATE in actions:
            assert actions.index(Action.CHANGE_STATE) < actions.index(entry)


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_the_robot_moves_only_when_a_person_commanded_it(state, event):
    """Homing only on `home`; a run only when a command starts one: never on entering IDLE."""
    decision = _decided(state, event)
    if decision is None:
        return
    if Action.START_HOMING in decision.actions:
        assert event is Event.HOME_REQUESTED
    if Action.START_RUN in decision.actions:
        assert event.value.endswith("_REQUESTED")


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_nothing_moves_or_sprays_on_the_way_into_error(state, event):
    decision = _decided(state, event)
    if decision is None or decision.target is not State.ERROR:
        return
    assert not {Action.START_RUN, Action.START_HOMING, Action.OPEN_GATE} & set(decision.actions)


@pytest.mark.parametrize(("state", "event"), PAIRS)
def test_paused_is_entered_only_after_the_valve_is_closed_and_the_robot_held(state, event):
    """Every way into PAUSED holds first (valve closed, robot stopped, the run holding),
    and nothing into PAUSED opens the gate or starts motion."""
    decision = _decided(state, event)
    if decision is None:
        return
    actions = list(decision.actions)
    if decision.target is State.PAUSED and decision.changes_state:
        assert actions[0] is Action.HOLD, f"{state} on {event}: {actions}"
        assert actions.index(Action.HOLD) < actions.index(Action.CHANGE_STATE)
        assert not {Action.OPEN_GATE, Action.START_RUN, Action.START_HOMING} & set(actions)
    else:
        assert Action.HOLD not in actions, f"{state} on {event}: {actions}"


def test_a_run_is_started_exactly_when_an_operational_state_is_entered_from_outside() -> None:
    for state, event in PAIRS:
        decision = _decided(state, event)
        if decision is None:
            continue
        entering = decision.target in OPERATIONAL_STATES and decision.source not in {
            State.EXECUTING_TRAJECTORY,
            State.PAUSED,
        }
        assert (Action.START_RUN in decision.actions) == entering, (state, event)


def test_every_row_has_its_actions_and_refusals_have_none() -> None:
    accepted = [pair for pair in PAIRS if _decided(*pair) is not None]
    assert len(accepted) == len(transitions())  # each row decides, and nothing else does
    for state, event in accepted:
        assert _decided(state, event).actions == actions_of(_decided(state, event).transition)

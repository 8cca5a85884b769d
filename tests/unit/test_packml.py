"""PackML as the cell shows it, checked against OPC 30050's published model.

The product's table of the standard (server/opcua/packml_model.py, the declarations
of server/opcua/packml_types.py) against the NodeSet's names, ids, numbers and
mandatory members; and the tracker (server/opcua/packml.py) over random walks through
the cell's own transition table: every PackML state change it makes is one of the
standard's transitions, however the cell's decisions and its state_changed messages
interleave.
"""

from __future__ import annotations

import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from server.core.machine.transitions import OPERATIONAL_STATES, TRANSITIONS, Event, State
from server.opcua import packml_model as model
from server.opcua.packml import PackMLState, PackMLTracker
from server.opcua.packml_types import DECLARATIONS, OBJECT_TYPES, STATE_NUMBER_IDS
from tests import packml_reference as reference


def test_the_table_names_the_standards_types_with_its_ids() -> None:
    ids = reference.node_ids()
    for name, number in (
        model.EXECUTE_STATE_MACHINE_TYPE,
        model.MACHINE_STATE_MACHINE_TYPE,
        model.BASE_STATE_MACHINE_TYPE,
        model.STATUS_OBJECT_TYPE,
        model.ADMIN_OBJECT_TYPE,
        model.BASE_OBJECT_TYPE,
        model.MODE_ENUM,
        model.COUNT_DATA_TYPE,
        model.ALARM_DATA_TYPE,
        model.DESCRIPTOR_DATA_TYPE,
    ):
        assert ids[name] == number, name
        assert reference.type_id(name) == f"ns=1;i={number}"
    for name, number, _ in (model.HAS_ALARM, model.HAS_WARNING, model.HAS_STOP_REASON):
        assert ids[name] == number


def test_the_states_have_the_standards_ids_and_numbers() -> None:
    numbers, ids = reference.state_numbers(), reference.state_ids()
    assert {node.name for node in model.STATE_NODES} == set(numbers)
    for node in model.STATE_NODES:
        assert numbers[node.name] == node.number, node
        assert ids[node.name] == f"ns=1;i={node.node_id}", node
    for state in PackMLState:
        assert numbers[state.browse_name] == int(state)
    # The StateNumber properties' ids, as the NodeSet gives them.
    assert reference.state_number_ids() == STATE_NUMBER_IDS


def test_the_transitions_are_the_standards() -> None:
    table = {(int(a), int(b)) for a, b in model.ALLOWED}
    assert table == reference.allowed()


def test_every_mandatory_member_is_declared_with_the_standards_id() -> None:
    for (name, number), _ in OBJECT_TYPES:
        declared = {member.name: member for member in DECLARATIONS[number]}
        for member in reference.members(name):
            if member.node_class not in ("Object", "Variable", "Method"):
                continue
            if member.mandatory:
                assert member.name in declared, (name, member.name)
            if member.name in declared:
                ours = declared[member.name]
                assert f"ns=1;i={ours.type_id}" == member.node_id, (name, member.name)
                assert ours.mandatory == member.mandatory, (name, member.name)


# --- the tracker over random walks through the cell's machine --------------------------

_SELF_LOOPS = {Event.ROBOT_READY, Event.VISION_READY, Event.GLUE_READY}


@st.composite
def walks(draw: st.DrawFn) -> list[tuple[str, int]]:
    return draw(st.lists(st.tuples(st.sampled_from(_STEPS), st.integers(0, 99)), max_size=60))


_STEPS = ("transition", "progress", "deliver", "packml-reset", "probe-refused")


@settings(max_examples=300, deadline=None)
@given(start=st.sampled_from([State.INITIALIZING, State.IDLE]), steps=walks())
def test_every_packml_change_is_one_the_standard_allows(
    start: State, steps: list[tuple[str, int]]
) -> None:
    tracker = PackMLTracker.of(start)
    seen = [tracker.state]
    state = start
    undelivered: list[tuple[State, State, Event]] = []  # state_changed not yet followed

    def entered(states: list[PackMLState]) -> None:
        seen.extend(states)

    for step, pick in steps:
        if step == "transition":
            rows = [
                row
                for row in TRANSITIONS[state].values()
                if row.event not in _SELF_LOOPS
                and not (row.event is Event.SYSTEM_READY and state is not State.INITIALIZING)
            ]
            row = rows[pick % len(rows)]
            if row.event is Event.RESET_REQUESTED:
                entered(tracker.probing(state, row.event))  # a reset probes first
            entered(tracker.accepted(state, row.event, row.target))
            if row.target is not state:
                undelivered.append((state, row.target, row.event))
            state = row.target
        elif step == "progress" and not undelivered:
            entered(tracker.progressed(state))
        elif step == "deliver" and undelivered:
            entered(tracker.settled(*undelivered.pop(0)))
        elif step == "packml-reset" and state is State.IDLE and not undelivered:
            if tracker.state in (PackMLState.STOPPED, PackMLState.COMPLETE):
                entered(tracker.resetting())
                entered(tracker.reset_done())
        elif step == "probe-refused" and state is State.ERROR:
            entered(tracker.probing(state, Event.RESET_REQUESTED))
            entered(tracker.refused(state, Event.RESET_REQUESTED))
    while undelivered:
        entered(tracker.settled(*undelivered.pop(0)))
    pairs = list(itertools.pairwise(seen))
    wrong = [(a.name, b.name) for a, b in pairs if (int(a), int(b)) not in reference.allowed()]
    assert not wrong, (wrong, [s.name for s in seen])
    assert tracker.skipped == 0
    assert tracker.state is _settled(state, tracker.state), (state, tracker.state)


def _settled(state: State, shown: PackMLState) -> PackMLState:
    """What PackML shows once every message is followed, for the cell's `state`."""
    S = PackMLState
    expected = {
        State.IDLE: {S.IDLE, S.STOPPED, S.COMPLETE},
        State.ERROR: {S.ABORTED},
        State.PAUSED: {S.HELD},
        State.INITIALIZING: {S.RESETTING},
    }.get(state, {S.STARTING, S.EXECUTE, S.UNHOLDING} if state in OPERATIONAL_STATES else set())
    return shown if shown in expected else S.CLEARING  # CLEARING: never the answer


def test_a_whole_day_in_packml_terms() -> None:
    S = PackMLState
    tracker = PackMLTracker.of(State.INITIALIZING)
    steps = [
        tracker.accepted(State.INITIALIZING, Event.SYSTEM_READY, State.IDLE),
        tracker.settled(State.INITIALIZING, State.IDLE, Event.SYSTEM_READY),
        tracker.accepted(State.IDLE, Event.START_REQUESTED, State.EXECUTING_TRAJECTORY),
        tracker.settled(State.IDLE, State.EXECUTING_TRAJECTORY, Event.START_REQUESTED),
        tracker.progressed(State.EXECUTING_TRAJECTORY),
        tracker.accepted(State.EXECUTING_TRAJECTORY, Event.PAUSE_REQUESTED, State.PAUSED),
        tracker.settled(State.EXECUTING_TRAJECTORY, State.PAUSED, Event.PAUSE_REQUESTED),
        tracker.accepted(State.PAUSED, Event.RESUME_REQUESTED, State.EXECUTING_TRAJECTORY),
        tracker.settled(State.PAUSED, State.EXECUTING_TRAJECTORY, Event.RESUME_REQUESTED),
        tracker.progressed(State.EXECUTING_TRAJECTORY),
        tracker.accepted(State.EXECUTING_TRAJECTORY, Event.OPERATION_COMPLETED, State.IDLE),
        tracker.settled(State.EXECUTING_TRAJECTORY, State.IDLE, Event.OPERATION_COMPLETED),
        tracker.resetting(),
        tracker.reset_done(),
        tracker.accepted(State.IDLE, Event.EMERGENCY_STOP, State.ERROR),
        tracker.settled(State.IDLE, State.ERROR, Event.EMERGENCY_STOP),
        tracker.probing(State.ERROR, Event.RESET_REQUESTED),
        tracker.accepted(State.ERROR, Event.RESET_REQUESTED, State.IDLE),
        tracker.settled(State.ERROR, State.IDLE, Event.RESET_REQUESTED),
    ]
    assert [s for step in steps for s in step] == [
        S.IDLE,
        S.STARTING,
        S.EXECUTE,
        S.HOLDING,
        S.HELD,
        S.UNHOLDING,
        S.EXECUTE,
        S.COMPLETING,
        S.COMPLETE,
        S.RESETTING,
        S.IDLE,
        S.ABORTING,
        S.ABORTED,
        S.CLEARING,
        S.STOPPED,
    ]

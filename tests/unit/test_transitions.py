"""The table, pair by pair, against the rules as the issue states them."""

from __future__ import annotations

import itertools

import pytest

from server.common.errors import GuardRefused, TransitionNotAllowed
from server.core.machine.actions import Action as A
from server.core.machine.engine import Facts, available_commands, check, step
from server.core.machine.transitions import COMMANDS, TRANSITIONS, Event, State, normalize_command

S, E = State, Event
OPERATIONAL = {
    S.CALIBRATING_ROBOT,
    S.CALIBRATING_CAMERA,
    S.EXECUTING_TRAJECTORY,
    S.CREATING_WORKPIECE,
    S.PAUSED,
}

# Written out by hand from the specification and the issue, independently of the module.
EXPECTED: dict[tuple[State, Event], State] = {
    (S.INITIALIZING, E.ROBOT_READY): S.INITIALIZING,
    (S.INITIALIZING, E.VISION_READY): S.INITIALIZING,
    (S.INITIALIZING, E.GLUE_READY): S.INITIALIZING,
    (S.INITIALIZING, E.SYSTEM_READY): S.IDLE,
    (S.IDLE, E.START_REQUESTED): S.EXECUTING_TRAJECTORY,
    (S.IDLE, E.CALIBRATE_ROBOT_REQUESTED): S.CALIBRATING_ROBOT,
    (S.IDLE, E.CALIBRATE_CAMERA_REQUESTED): S.CALIBRATING_CAMERA,
    (S.IDLE, E.CREATE_WORKPIECE_REQUESTED): S.CREATING_WORKPIECE,
    (S.IDLE, E.HOME_REQUESTED): S.IDLE,
    (S.IDLE, E.JOG_REQUESTED): S.IDLE,
    (S.IDLE, E.PURGE_REQUESTED): S.IDLE,
    (S.EXECUTING_TRAJECTORY, E.OPERATION_COMPLETED): S.IDLE,
    (S.EXECUTING_TRAJECTORY, E.CANCEL_REQUESTED): S.IDLE,
    (S.EXECUTING_TRAJECTORY, E.PAUSE_REQUESTED): S.PAUSED,
    (S.PAUSED, E.RESUME_REQUESTED): S.EXECUTING_TRAJECTORY,
    (S.PAUSED, E.CANCEL_REQUESTED): S.IDLE,
    (S.PAUSED, E.OPERATION_COMPLETED): S.IDLE,
    (S.ERROR, E.RESET_REQUESTED): S.IDLE,
}
for _state in (S.CALIBRATING_ROBOT, S.CALIBRATING_CAMERA, S.CREATING_WORKPIECE):
    EXPECTED[(_state, E.OPERATION_COMPLETED)] = S.IDLE
    EXPECTED[(_state, E.CANCEL_REQUESTED)] = S.IDLE
for _state in OPERATIONAL:
    EXPECTED[(_state, E.OPERATION_FAILED)] = S.ERROR
for _state in State:
    EXPECTED[(_state, E.EMERGENCY_STOP)] = S.ERROR
    EXPECTED[(_state, E.ERROR_OCCURRED)] = S.ERROR

ALL_READY = Facts(ready_devices=frozenset({"robot", "camera", "glue"}))
PAIRS = list(itertools.product(State, Event))


@pytest.mark.parametrize(("state", "event"), PAIRS, ids=[f"{s}-{e}" for s, e in PAIRS])
def test_every_pair_is_allowed_or_refused_as_specified(state: State, event: Event) -> None:
    expected = EXPECTED.get((state, event))
    if expected is None:
        with pytest.raises(TransitionNotAllowed) as refusal:
            step(state, event, ALL_READY)
        assert refusal.value.state == state.value and refusal.value.event == event.value
    else:
        assert step(state, event, ALL_READY).target is expected


def test_table_has_no_row_beyond_the_expected_ones() -> None:
    rows = {(s, e): row.target for s, rows in TRANSITIONS.items() for e, row in rows.items()}
    assert rows == EXPECTED


def test_refusal_message_names_the_command_and_the_state() -> None:
    with pytest.raises(TransitionNotAllowed, match="start is not allowed in CALIBRATING_ROBOT"):
        step(S.CALIBRATING_ROBOT, E.START_REQUESTED)


def test_system_ready_waits_for_every_device() -> None:
    partly = Facts(ready_devices=frozenset({"robot", "glue"}))
    with pytest.raises(GuardRefused, match="waiting for camera"):
        step(S.INITIALIZING, E.SYSTEM_READY, partly)
    assert step(S.INITIALIZING, E.SYSTEM_READY, ALL_READY).target is S.IDLE


def test_reset_is_refused_while_a_fault_is_active_and_says_which() -> None:
    faulty = Facts(active_faults=("robot: connection refused",))
    with pytest.raises(GuardRefused, match="robot: connection refused"):
        step(S.ERROR, E.RESET_REQUESTED, faulty)
    assert step(S.ERROR, E.RESET_REQUESTED, Facts()).target is S.IDLE


def test_operation_lifecycle_actions() -> None:
    start = step(S.IDLE, E.START_REQUESTED)
    assert A.START_RUN in start.actions and A.CANCEL_RUN not in start.actions
    pause = step(S.EXECUTING_TRAJECTORY, E.PAUSE_REQUESTED)
    resume = step(S.PAUSED, E.RESUME_REQUESTED)
    for decision in (pause, resume):  # one run spans EXECUTING and PAUSED
        assert A.START_RUN not in decision.actions and A.CANCEL_RUN not in decision.actions
    assert A.HOLD in pause.actions and A.OPEN_GATE in resume.actions
    for state in OPERATIONAL:
        assert A.CANCEL_RUN in step(state, E.EMERGENCY_STOP).actions
    assert not step(S.ERROR, E.ERROR_OCCURRED).changes_state


def test_available_commands_follow_the_table() -> None:
    assert available_commands(S.IDLE) == [
        "start",
        "calibrate-robot",
        "calibrate-camera",
        "create-workpiece",
        "estop",
        "home",
        "jog",
        "purge",
    ]
    assert available_commands(S.EXECUTING_TRAJECTORY) == ["pause", "cancel", "estop"]
    assert available_commands(S.PAUSED) == ["resume", "cancel", "estop"]
    assert available_commands(S.ERROR, Facts(active_faults=("glue: no reply",))) == ["estop"]
    assert "reset" in available_commands(S.ERROR)
    for state in State:  # the software stop is always available
        assert "estop" in available_commands(state)


def test_check_gives_a_reason_either_way() -> None:
    assert check(S.IDLE, E.START_REQUESTED) == (
        True,
        "start is allowed in IDLE (→ EXECUTING_TRAJECTORY)",
    )
    assert check(S.PAUSED, E.START_REQUESTED) == (False, "start is not allowed in PAUSED")


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("start", "start"),
        ("START", "start"),
        ("calibrate_robot", "calibrate-robot"),
        ("create_workpiece", "create-workpiece"),
        ("emergency_stop", "estop"),
        ("bogus", None),
    ],
)
def test_command_names_are_forgiving_about_case_and_underscores(given, expected) -> None:
    assert normalize_command(given) == expected
    if expected:
        assert expected in COMMANDS

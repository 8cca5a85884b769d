"""The cell's states, events and transition table: the one place they are declared.

Theory of operation
-------------------
The cell is always in exactly one `State`. Something that happens (a request
from the HMI, a device coming up, an operation finishing, a fault) is an
`Event`. The table `TRANSITIONS` says, for each state, which events it accepts
and which state follows. An event with no entry is refused and the state is
unchanged; nothing else in the code base decides a transition.

Some transitions carry a *guard*: a named condition on facts the worker
gathers (are all devices ready? is every fault cleared?). The guard is part of
the table, so the engine, the "allowed now?" query, the diagram and the tests
all see it.

Three rules are written as rules rather than rows, because they hold for every
state and spelling them out per state would invite a typo:

* EMERGENCY_STOP and ERROR_OCCURRED lead to ERROR from every state
  (from ERROR itself they are accepted and stay in ERROR: another fault is
  recorded, the first-out stop reason is kept).
* OPERATION_FAILED leads to ERROR from every state that runs an operation.

Operational states run an operation (a background task) while the cell is in
them. A trajectory run spans EXECUTING_TRAJECTORY *and* PAUSED: pausing stops
the arm where it is with the valve closed (PAUSED once both are confirmed),
resuming continues the interrupted segment from there, so the task lives
across both states and is cancelled only when the cell leaves that pair.

Commands are the operator's names for the request events (`start`,
`calibrate-robot`, ...). They are what the HTTP API, the CLI and the
`can_execute_operation` query speak.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType
from typing import Final


class State(StrEnum):
    """Where the cell is."""

    INITIALIZING = "INITIALIZING"
    IDLE = "IDLE"
    CALIBRATING_ROBOT = "CALIBRATING_ROBOT"
    CALIBRATING_CAMERA = "CALIBRATING_CAMERA"
    EXECUTING_TRAJECTORY = "EXECUTING_TRAJECTORY"
    CREATING_WORKPIECE = "CREATING_WORKPIECE"
    PAUSED = "PAUSED"
    ERROR = "ERROR"


class Event(StrEnum):
    """What can happen to the cell."""

    SYSTEM_READY = "SYSTEM_READY"
    ROBOT_READY = "ROBOT_READY"
    VISION_READY = "VISION_READY"
    GLUE_READY = "GLUE_READY"
    START_REQUESTED = "START_REQUESTED"
    CALIBRATE_ROBOT_REQUESTED = "CALIBRATE_ROBOT_REQUESTED"
    CALIBRATE_CAMERA_REQUESTED = "CALIBRATE_CAMERA_REQUESTED"
    CREATE_WORKPIECE_REQUESTED = "CREATE_WORKPIECE_REQUESTED"
    PAUSE_REQUESTED = "PAUSE_REQUESTED"
    RESUME_REQUESTED = "RESUME_REQUESTED"
    CANCEL_REQUESTED = "CANCEL_REQUESTED"
    OPERATION_COMPLETED = "OPERATION_COMPLETED"
    OPERATION_FAILED = "OPERATION_FAILED"
    ERROR_OCCURRED = "ERROR_OCCURRED"
    EMERGENCY_STOP = "EMERGENCY_STOP"
    RESET_REQUESTED = "RESET_REQUESTED"
    HOME_REQUESTED = "HOME_REQUESTED"
    JOG_REQUESTED = "JOG_REQUESTED"
    PURGE_REQUESTED = "PURGE_REQUESTED"


class Guard(StrEnum):
    """Named conditions a transition may require; evaluated by the engine on `Facts`."""

    ALL_DEVICES_READY = "all devices ready"
    FAULTS_CLEARED = "faults cleared"


@dataclass(frozen=True, slots=True)
class Transition:
    """One row of the table: in `source`, `event` leads to `target` if `guard` holds."""

    source: State
    event: Event
    target: State
    guard: Guard | None = None


# Which operation each operational state runs (the names of server/core/operations).
OPERATION_OF_STATE: Final = MappingProxyType(
    {
        State.EXECUTING_TRAJECTORY: "trajectory",
        State.PAUSED: "trajectory",
        State.CALIBRATING_ROBOT: "calibrate_robot",
        State.CALIBRATING_CAMERA: "calibrate_camera",
        State.CREATING_WORKPIECE: "create_workpiece",
    }
)
OPERATIONAL_STATES: Final = frozenset(OPERATION_OF_STATE)

# Readiness events reported by the devices while INITIALIZING.
READINESS_EVENTS: Final = MappingProxyType(
    {Event.ROBOT_READY: "robot", Event.VISION_READY: "camera", Event.GLUE_READY: "glue"}
)

_ROWS: Final[tuple[Transition, ...]] = (
    # Start-up: each device reports ready; SYSTEM_READY follows once all have.
    Transition(State.INITIALIZING, Event.ROBOT_READY, State.INITIALIZING),
    Transition(State.INITIALIZING, Event.VISION_READY, State.INITIALIZING),
    Transition(State.INITIALIZING, Event.GLUE_READY, State.INITIALIZING),
    Transition(State.INITIALIZING, Event.SYSTEM_READY, State.IDLE, Guard.ALL_DEVICES_READY),
    # Ready: one operation at a time.
    Transition(State.IDLE, Event.START_REQUESTED, State.EXECUTING_TRAJECTORY),
    Transition(State.IDLE, Event.CALIBRATE_ROBOT_REQUESTED, State.CALIBRATING_ROBOT),
    Transition(State.IDLE, Event.CALIBRATE_CAMERA_REQUESTED, State.CALIBRATING_CAMERA),
    Transition(State.IDLE, Event.CREATE_WORKPIECE_REQUESTED, State.CREATING_WORKPIECE),
    # A person sends the robot to its safe position; the cell stays IDLE while it moves.
    Transition(State.IDLE, Event.HOME_REQUESTED, State.IDLE),
    # Maintenance moves the robot one bounded step (teaching marker positions); stays IDLE.
    Transition(State.IDLE, Event.JOG_REQUESTED, State.IDLE),
    # Maintenance purges the glue line over the purge cup: an activity in IDLE, like home.
    Transition(State.IDLE, Event.PURGE_REQUESTED, State.IDLE),
    # Spraying: finish, cancel or pause.
    Transition(State.EXECUTING_TRAJECTORY, Event.OPERATION_COMPLETED, State.IDLE),
    Transition(State.EXECUTING_TRAJECTORY, Event.CANCEL_REQUESTED, State.IDLE),
    Transition(State.EXECUTING_TRAJECTORY, Event.PAUSE_REQUESTED, State.PAUSED),
    Transition(State.PAUSED, Event.RESUME_REQUESTED, State.EXECUTING_TRAJECTORY),
    Transition(State.PAUSED, Event.CANCEL_REQUESTED, State.IDLE),
    # A pause as the run finishes its last move: the run ends while held.
    Transition(State.PAUSED, Event.OPERATION_COMPLETED, State.IDLE),
    # Calibrations and workpiece creation: finish or cancel.
    Transition(State.CALIBRATING_ROBOT, Event.OPERATION_COMPLETED, State.IDLE),
    Transition(State.CALIBRATING_ROBOT, Event.CANCEL_REQUESTED, State.IDLE),
    Transition(State.CALIBRATING_CAMERA, Event.OPERATION_COMPLETED, State.IDLE),
    Transition(State.CALIBRATING_CAMERA, Event.CANCEL_REQUESTED, State.IDLE),
    Transition(State.CREATING_WORKPIECE, Event.OPERATION_COMPLETED, State.IDLE),
    Transition(State.CREATING_WORKPIECE, Event.CANCEL_REQUESTED, State.IDLE),
    # Leaving ERROR takes a person, and only once the cause is gone.
    Transition(State.ERROR, Event.RESET_REQUESTED, State.IDLE, Guard.FAULTS_CLEARED),
)


def _build_table() -> dict[State, dict[Event, Transition]]:
    table: dict[State, dict[Event, Transition]] = {state: {} for state in State}
    rows = list(_ROWS)
    for state in State:
        rows.append(Transition(state, Event.EMERGENCY_STOP, State.ERROR))
        rows.append(Transition(state, Event.ERROR_OCCURRED, State.ERROR))
    for state in OPERATIONAL_STATES:
        rows.append(Transition(state, Event.OPERATION_FAILED, State.ERROR))
    for row in rows:
        if row.event in table[row.source]:
            raise ValueError(f"duplicate transition for {row.source} on {row.event}")
        table[row.source][row.event] = row
    return table


TRANSITIONS: Final = MappingProxyType(
    {state: MappingProxyType(rows) for state, rows in _build_table().items()}
)


class Command(StrEnum):
    """The operator's names for the request events: what HTTP, the CLI and the façade speak."""

    START = "start"
    CALIBRATE_ROBOT = "calibrate-robot"
    CALIBRATE_CAMERA = "calibrate-camera"
    CREATE_WORKPIECE = "create-workpiece"
    PAUSE = "pause"
    RESUME = "resume"
    CANCEL = "cancel"
    ESTOP = "estop"
    RESET = "reset"
    HOME = "home"
    JOG = "jog"
    PURGE = "purge"


# The event each command posts.
COMMANDS: Final = MappingProxyType(
    {
        Command.START: Event.START_REQUESTED,
        Command.CALIBRATE_ROBOT: Event.CALIBRATE_ROBOT_REQUESTED,
        Command.CALIBRATE_CAMERA: Event.CALIBRATE_CAMERA_REQUESTED,
        Command.CREATE_WORKPIECE: Event.CREATE_WORKPIECE_REQUESTED,
        Command.PAUSE: Event.PAUSE_REQUESTED,
        Command.RESUME: Event.RESUME_REQUESTED,
        Command.CANCEL: Event.CANCEL_REQUESTED,
        Command.ESTOP: Event.EMERGENCY_STOP,
        Command.RESET: Event.RESET_REQUESTED,
        Command.HOME: Event.HOME_REQUESTED,
        Command.JOG: Event.JOG_REQUESTED,
        Command.PURGE: Event.PURGE_REQUESTED,
    }
)
COMMAND_OF_EVENT: Final = MappingProxyType({event: name for name, event in COMMANDS.items()})
_ALIASES: Final = MappingProxyType(
    {"emergency-stop": Command.ESTOP, "calibrate": Command.CALIBRATE_ROBOT}
)


def normalize_command(name: str) -> Command | None:
    """The command `name` means (case and `_`/`-` forgiven, a few aliases), or None."""
    canonical = name.strip().lower().replace("_", "-")
    if canonical in _ALIASES:
        return _ALIASES[canonical]
    try:
        return Command(canonical)
    except ValueError:
        return None


def transitions() -> list[Transition]:
    """Every row of the table, in declaration order per state."""
    return [row for rows in TRANSITIONS.values() for row in rows.values()]


def event_label(event: Event) -> str:
    """How an event reads in messages: the command name where it has one."""
    command = COMMAND_OF_EVENT.get(event)
    return command.value if command is not None else event.value

"""OPC 30050 (PackML) v1.1 as the cell uses it: the standard's names, numeric node ids,
state numbers and transitions, written out once. Pure data, no I/O.

The address space is built by the cell's own code from this table
(server/opcua/packml_types.py); the standard's published NodeSet is not read by
the product. The tests check this table against that NodeSet
(tests/reference/packml/), so a wrong id or name here fails a test, not a
SCADA binding.

Only what the cell's instance uses is declared: the four object types of the
base object (with their mandatory members and the optional ones the cell
fills), the three nested state machines, the mode enumeration and the alarm,
count and descriptor structures.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Final

NAMESPACE_URI: Final = "http://opcfoundation.org/UA/PackML/"
VERSION: Final = "1.01"  # the model version of OPC 30050 v1.1's NodeSet

# Object types, data types and reference types: (browse name, numeric id in NAMESPACE_URI).
EXECUTE_STATE_MACHINE_TYPE: Final = ("PackMLExecuteStateMachineType", 1)
MACHINE_STATE_MACHINE_TYPE: Final = ("PackMLMachineStateMachineType", 2)
BASE_STATE_MACHINE_TYPE: Final = ("PackMLBaseStateMachineType", 3)
STATUS_OBJECT_TYPE: Final = ("PackMLStatusObjectType", 4)
ADMIN_OBJECT_TYPE: Final = ("PackMLAdminObjectType", 5)
BASE_OBJECT_TYPE: Final = ("PackMLBaseObjectType", 6)
MODE_ENUM: Final = ("ProductionMaintenanceModeEnum", 11)
COUNT_DATA_TYPE: Final = ("PackMLCountDataType", 14)
ALARM_DATA_TYPE: Final = ("PackMLAlarmDataType", 15)
DESCRIPTOR_DATA_TYPE: Final = ("PackMLDescriptorDataType", 16)
HAS_ALARM: Final = ("HasAlarm", 22, "AlarmFor")
HAS_WARNING: Final = ("HasWarning", 24, "WarningFor")
HAS_STOP_REASON: Final = ("HasStopReason", 25, "StopReasonFor")


class PackMLState(IntEnum):
    """The standard's StateNumber of each of its 17 states (and of its two super-states)."""

    CLEARING = 1
    STOPPED = 2
    STARTING = 3
    IDLE = 4
    SUSPENDED = 5
    EXECUTE = 6
    STOPPING = 7
    ABORTING = 8
    ABORTED = 9
    HOLDING = 10
    HELD = 11
    UNHOLDING = 12
    SUSPENDING = 13
    UNSUSPENDING = 14
    RESETTING = 15
    COMPLETING = 16
    COMPLETE = 17

    @property
    def browse_name(self) -> str:
        return self.name.capitalize()


class UnitMode(IntEnum):
    """ProductionMaintenanceModeEnum's values."""

    INVALID = 0
    PRODUCE = 1
    MAINTENANCE = 2
    MANUAL = 3

    @property
    def browse_name(self) -> str:
        return self.name.capitalize()


class Level(IntEnum):
    """Which of the three nested state machines a state belongs to."""

    BASE = 0  # PackMLBaseStateMachineType: Aborting, Aborted, Cleared
    MACHINE = 1  # PackMLMachineStateMachineType (Cleared's sub-machine): Stopped, Running...
    EXECUTE = 2  # PackMLExecuteStateMachineType (Running's sub-machine): Idle, Execute...


@dataclass(frozen=True)
class StateNode:
    """A state object of a state machine type: its id, level and StateNumber."""

    name: str
    node_id: int
    level: Level
    number: int


# The states of the three machine types, with the standard's ids. Cleared (19) and
# Running (18) are the super-states the two sub-machines live in.
STATE_NODES: Final = (
    StateNode("Resetting", 27, Level.EXECUTE, 15),
    StateNode("Idle", 28, Level.EXECUTE, 4),
    StateNode("Starting", 29, Level.EXECUTE, 3),
    StateNode("Suspending", 30, Level.EXECUTE, 13),
    StateNode("Suspended", 31, Level.EXECUTE, 5),
    StateNode("Unsuspending", 32, Level.EXECUTE, 14),
    StateNode("Holding", 33, Level.EXECUTE, 10),
    StateNode("Held", 34, Level.EXECUTE, 11),
    StateNode("Unholding", 35, Level.EXECUTE, 12),
    StateNode("Execute", 36, Level.EXECUTE, 6),
    StateNode("Completing", 37, Level.EXECUTE, 16),
    StateNode("Complete", 38, Level.EXECUTE, 17),
    StateNode("Stopped", 53, Level.MACHINE, 2),
    StateNode("Stopping", 54, Level.MACHINE, 7),
    StateNode("Clearing", 55, Level.MACHINE, 1),
    StateNode("Running", 75, Level.MACHINE, 18),
    StateNode("Aborting", 61, Level.BASE, 8),
    StateNode("Aborted", 62, Level.BASE, 9),
    StateNode("Cleared", 71, Level.BASE, 19),
)
STATE_NODE: Final = MappingProxyType({node.name: node for node in STATE_NODES})
RUNNING, CLEARED = STATE_NODE["Running"], STATE_NODE["Cleared"]


def path_of(state: PackMLState) -> tuple[StateNode, ...]:
    """The state each machine is in when the unit is in `state`, outermost first:
    Execute is (Cleared, Running, Execute); Stopped is (Cleared, Stopped); Aborted is
    (Aborted,)."""
    node = STATE_NODE[state.browse_name]
    if node.level is Level.EXECUTE:
        return (CLEARED, RUNNING, node)
    if node.level is Level.MACHINE:
        return (CLEARED, node)
    return (node,)


_EXECUTE_STATES: Final = frozenset(
    PackMLState[node.name.upper()] for node in STATE_NODES if node.level is Level.EXECUTE
)
_CLEARED_STATES: Final = _EXECUTE_STATES | {
    PackMLState.STOPPED,
    PackMLState.STOPPING,
    PackMLState.CLEARING,
}
S = PackMLState
# The transitions of the three machines, flattened to the 17 states: each machine's
# own, then its super-state's (Running → Stopping from every Running state, Cleared →
# Aborting from every Cleared state; a super-state is entered at its first state:
# Running at Resetting, Cleared at Clearing).
ALLOWED: Final = frozenset(
    {
        (S.RESETTING, S.IDLE),
        (S.IDLE, S.STARTING),
        (S.STARTING, S.EXECUTE),
        (S.STARTING, S.HOLDING),
        (S.EXECUTE, S.SUSPENDING),
        (S.SUSPENDING, S.SUSPENDED),
        (S.SUSPENDING, S.HOLDING),
        (S.SUSPENDED, S.UNSUSPENDING),
        (S.SUSPENDED, S.HOLDING),
        (S.UNSUSPENDING, S.EXECUTE),
        (S.UNSUSPENDING, S.HOLDING),
        (S.EXECUTE, S.HOLDING),
        (S.HOLDING, S.HELD),
        (S.HELD, S.UNHOLDING),
        (S.UNHOLDING, S.EXECUTE),
        (S.UNHOLDING, S.HOLDING),
        (S.EXECUTE, S.COMPLETING),
        (S.COMPLETING, S.COMPLETE),
        (S.COMPLETE, S.RESETTING),
        (S.STOPPING, S.STOPPED),
        (S.CLEARING, S.STOPPED),
        (S.STOPPED, S.RESETTING),
        (S.ABORTING, S.ABORTED),
        (S.ABORTED, S.CLEARING),
    }
    | {(state, S.STOPPING) for state in _EXECUTE_STATES}
    | {(state, S.ABORTING) for state in _CLEARED_STATES}
)

"""The cell's 8 states on PackML's 17 (OPC 30050, ISA-TR88.00.02), declared once.

Why a table and not a state machine: the cell's own machine (server/core/machine/transitions.py)
is the one that decides; PackML is a way of showing it to a plant that reads
PackTags. Each state's reason is in docs/plant-integration.md. Pure: no I/O.
"""

from __future__ import annotations

from enum import IntEnum
from types import MappingProxyType
from typing import Final

from server.core.machine.transitions import State


class PackMLState(IntEnum):
    """PackTags StateCurrent numbers."""

    UNDEFINED = 0
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


class UnitMode(IntEnum):
    """PackTags UnitModeCurrent numbers (the three modes PackML defines)."""

    PRODUCTION = 1
    MAINTENANCE = 2
    MANUAL = 3


PACKML_STATE: Final = MappingProxyType(
    {
        State.INITIALIZING: PackMLState.RESETTING,
        State.IDLE: PackMLState.IDLE,
        State.EXECUTING_TRAJECTORY: PackMLState.EXECUTE,
        State.PAUSED: PackMLState.HELD,
        State.CALIBRATING_ROBOT: PackMLState.EXECUTE,
        State.CALIBRATING_CAMERA: PackMLState.EXECUTE,
        State.CREATING_WORKPIECE: PackMLState.EXECUTE,
        State.ERROR: PackMLState.ABORTED,
    }
)

# The states that run maintenance work rather than production.
MAINTENANCE_STATES: Final = frozenset(
    {State.CALIBRATING_ROBOT, State.CALIBRATING_CAMERA, State.CREATING_WORKPIECE}
)


def packml_state(state: State) -> PackMLState:
    """StateCurrent for the cell's `state`."""
    return PACKML_STATE[state]


def unit_mode(state: State) -> UnitMode:
    """UnitModeCurrent: Maintenance while calibrating or teaching a part, else Production."""
    return UnitMode.MAINTENANCE if state in MAINTENANCE_STATES else UnitMode.PRODUCTION

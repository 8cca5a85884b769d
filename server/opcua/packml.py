"""The cell's 8 states and its transitions on PackML's 17 states: `PackMLTracker`. Pure.

The cell's own machine (server/core/machine/transitions.py) decides; PackML is
how a plant sees it. The cell decides a transition in one step, but its acting
work (the halt, the hold, a reset's probe of the devices, the start of a run)
happens between the decision and the new state, or after it: PackML's acting
states (Stopping, Holding, Aborting, Clearing, Completing, Starting,
Unholding, Resetting) are shown exactly while that work is under way, from
three things the cell says:

- the worker's verdict, before its first action (server/core/worker/decisions.py):
  the acting state begins (Stopping as the halt begins, Holding as the hold does);
- the new state, once entered (a `state_changed` bus message): the settled state
  (Stopped, Held, Aborted...);
- the run's first step (a `progress` message in the operation's state): Starting
  and Unholding end in Execute once the run moves again.

Plus PackML's own Reset (Stopped or Complete → Resetting → Idle), which the
interface runs as a live probe of every device (server/opcua/packml_methods.py).

Every state change the tracker makes is one of the standard's transitions
(`ALLOWED`, checked against the published model by the tests); it never
changes the cell. docs/plant-integration.md has the table.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Final

from server.core.machine.transitions import OPERATIONAL_STATES, Event, State
from server.opcua.packml_model import ALLOWED, PackMLState, UnitMode

__all__ = ["ALLOWED", "PackMLState", "PackMLTracker", "UnitMode", "packml_state", "unit_mode"]

S = PackMLState

# The state shown for the cell's state when nothing more is known (at start-up, or
# after the follower caught up with the bus): its settled PackML state.
PACKML_STATE: Final = MappingProxyType(
    {
        State.INITIALIZING: S.RESETTING,
        State.IDLE: S.IDLE,
        State.EXECUTING_TRAJECTORY: S.EXECUTE,
        State.PAUSED: S.HELD,
        State.CALIBRATING_ROBOT: S.EXECUTE,
        State.CALIBRATING_CAMERA: S.EXECUTE,
        State.CREATING_WORKPIECE: S.EXECUTE,
        State.ERROR: S.ABORTED,
    }
)

# The states that run maintenance work rather than production.
MAINTENANCE_STATES: Final = frozenset(
    {State.CALIBRATING_ROBOT, State.CALIBRATING_CAMERA, State.CREATING_WORKPIECE}
)
# The requests that begin an operation from IDLE, and the mode it runs in.
_STARTS: Final = MappingProxyType(
    {
        Event.START_REQUESTED: UnitMode.PRODUCE,
        Event.CALIBRATE_ROBOT_REQUESTED: UnitMode.MAINTENANCE,
        Event.CALIBRATE_CAMERA_REQUESTED: UnitMode.MAINTENANCE,
        Event.CREATE_WORKPIECE_REQUESTED: UnitMode.MAINTENANCE,
    }
)
_FAULTS: Final = frozenset({Event.EMERGENCY_STOP, Event.ERROR_OCCURRED, Event.OPERATION_FAILED})
# Where each acting state settles: StateRequested while it acts.
SETTLES_IN: Final = MappingProxyType(
    {
        S.RESETTING: S.IDLE,
        S.STARTING: S.EXECUTE,
        S.UNHOLDING: S.EXECUTE,
        S.HOLDING: S.HELD,
        S.COMPLETING: S.COMPLETE,
        S.STOPPING: S.STOPPED,
        S.ABORTING: S.ABORTED,
        S.CLEARING: S.STOPPED,
        S.SUSPENDING: S.SUSPENDED,
        S.UNSUSPENDING: S.EXECUTE,
    }
)


def packml_state(state: State) -> PackMLState:
    """The settled PackML state of the cell's `state`."""
    return PACKML_STATE[state]


def unit_mode(state: State) -> UnitMode:
    """The mode: Maintenance while calibrating or teaching a part, else Produce."""
    return UnitMode.MAINTENANCE if state in MAINTENANCE_STATES else UnitMode.PRODUCE


@dataclass
class PackMLTracker:
    """The unit's PackML state and mode, moved by what the cell says (module docstring).

    Each method returns the states entered, in order (empty: no change); `state` and
    `mode` are the current ones. `skipped` counts the changes that were not one of the
    standard's transitions (zero unless the follower lost messages and caught up).
    """

    state: PackMLState
    mode: UnitMode = UnitMode.PRODUCE
    skipped: int = 0
    # The transition accepted last, until its state_changed arrives; and those settled
    # early because the worker decided the next event first (`_flush`).
    pending: tuple[State, State, Event] | None = None
    early: deque[tuple[State, State, Event]] = field(default_factory=deque)

    @classmethod
    def of(cls, state: State) -> PackMLTracker:
        """A tracker starting where the cell is (the server's start, a catch-up)."""
        return cls(packml_state(state), unit_mode(state))

    @property
    def requested(self) -> PackMLState:
        """StateRequested: the state the acting state leads to, or the current one."""
        return SETTLES_IN.get(self.state, self.state)

    def _go(self, *path: PackMLState) -> list[PackMLState]:
        """Walk `path` from where the unit is: the part of it already behind is left out."""
        if self.state in path:
            path = path[path.index(self.state) + 1 :]
        entered = []
        for step in path:
            if (self.state, step) not in ALLOWED:
                self.skipped += 1
            self.state = step
            entered.append(step)
        return entered

    def _starting(self, mode: UnitMode) -> list[PackMLState]:
        # A start from another door (HTTP, MQTT) while PackML waits for its Reset in
        # Stopped or Complete: the cell has accepted it, so the unit passes Resetting
        # and Idle to Starting at once (PackML's Start is only taken in Idle).
        self.mode = mode
        return self._go(S.RESETTING, S.IDLE, S.STARTING)

    def _flush(self, source: State) -> list[PackMLState]:
        """The worker decides in `source`, so the transition into it is complete even if
        its state_changed has not arrived yet: settle it now, and skip it when it does."""
        pending = self.pending
        if pending is None or pending[1] is not source:
            return []
        self.pending = None
        self.early.append(pending)
        return self._settle(*pending)

    def accepted(self, source: State, event: Event, target: State) -> list[PackMLState]:
        """The worker accepted `event` in `source` and begins to act: the acting state."""
        entered = self._flush(source)
        self.pending = (source, target, event) if target is not source else None
        return entered + self._acting(source, event, target)

    def _acting(self, source: State, event: Event, target: State) -> list[PackMLState]:
        if event in _FAULTS and target is State.ERROR:
            return [] if self.state in (S.ABORTING, S.ABORTED) else self._go(S.ABORTING)
        if event is Event.CANCEL_REQUESTED:
            return self._go(S.STOPPING)
        if event is Event.PAUSE_REQUESTED:
            return self._go(S.HOLDING)
        if event is Event.RESUME_REQUESTED:
            return self._go(S.UNHOLDING)
        if event in _STARTS and source is State.IDLE:
            return self._starting(_STARTS[event])
        if event is Event.OPERATION_COMPLETED:
            if source is State.PAUSED:  # the run ended while held: Held has no Complete
                return self._go(S.STOPPING)
            return self._go(S.EXECUTE, S.COMPLETING)
        if event is Event.RESET_REQUESTED and source is State.ERROR:
            return self._go(S.CLEARING)
        return []

    def probing(self, source: State, event: Event) -> list[PackMLState]:
        """A reset went to probe every device before it is decided: Clearing."""
        entered = self._flush(source)
        if event is Event.RESET_REQUESTED and source is State.ERROR:
            return entered + self._go(S.CLEARING)
        return entered

    def refused(self, source: State, event: Event) -> list[PackMLState]:
        """A reset refused on its probe's findings: the cell stays in ERROR, and Clearing
        (which has no way back to Aborted) ends through Aborting."""
        entered = self._flush(source)
        if event is Event.RESET_REQUESTED and self.state is S.CLEARING:
            return entered + self._go(S.ABORTING, S.ABORTED)
        return entered

    def settled(self, old: State, new: State, event: Event) -> list[PackMLState]:
        """The cell entered `new` from `old` on `event`: the settled state."""
        if self.early and self.early[0] == (old, new, event):
            self.early.popleft()  # settled already, when the next event was decided
            return []
        if self.pending == (old, new, event):
            self.pending = None
        return self._settle(old, new, event)

    def _settle(self, old: State, new: State, event: Event) -> list[PackMLState]:
        if new is State.ERROR:
            return self._go(S.ABORTING, S.ABORTED)
        if new is State.IDLE:
            if old is State.INITIALIZING:
                return self._go(S.RESETTING, S.IDLE)
            if old is State.ERROR:
                return self._go(S.CLEARING, S.STOPPED)
            if event is Event.OPERATION_COMPLETED and old is not State.PAUSED:
                return self._go(S.EXECUTE, S.COMPLETING, S.COMPLETE)
            if old in OPERATIONAL_STATES:  # cancelled, or finished while held
                return self._go(S.STOPPING, S.STOPPED)
            return []
        if new is State.PAUSED:
            return self._go(S.HOLDING, S.HELD)
        if new is State.EXECUTING_TRAJECTORY and old is State.PAUSED:
            return self._go(S.UNHOLDING)
        if new in OPERATIONAL_STATES and old is State.IDLE:
            return self._starting(unit_mode(new))
        if new is State.INITIALIZING:
            return self._go(S.RESETTING)
        return []

    def progressed(self, state: State) -> list[PackMLState]:
        """The running operation reported a step in `state`: Starting or Unholding is over."""
        running = state in OPERATIONAL_STATES and state is not State.PAUSED
        if running and self.state in (S.STARTING, S.UNHOLDING):
            return self._go(S.EXECUTE)
        return []

    def resetting(self) -> list[PackMLState]:
        """PackML's Reset accepted in Stopped or Complete: the devices are being probed."""
        self.mode = UnitMode.PRODUCE
        return self._go(S.RESETTING)

    def reset_done(self) -> list[PackMLState]:
        """Every device answered the Reset's probe: Idle (unless something else came first)."""
        return self._go(S.IDLE) if self.state is S.RESETTING else []

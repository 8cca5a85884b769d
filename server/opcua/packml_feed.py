"""Writes the PackML view of the cell: the state machines' CurrentState, Status and Admin.

`PackMLFeed` holds the `PackMLTracker` (server/opcua/packml.py) and writes each
state it enters, in order, under one lock: the three nested machines'
CurrentState (name, Id, Number), Status.StateCurrent, StateRequested and
UnitModeCurrent, stamped with when the cell said so. It is fed from two sides:
the worker's verdicts, as they are made (`decided`, a listener that never
blocks the worker: it only notes the states and leaves their writing to a task),
and the bus follower of server/opcua/interface.py (`settled`, `progressed`),
which writes once the command's answer has gone. Admin's time arrays, stop
reason, alarms and warnings are written here too.

The state and mode times count from the OPC UA server's start (AccTimeSinceReset):
the cell's journal keeps its own states' times (Admin.TimeInState), not PackML's.
"""

from __future__ import annotations

import asyncio
import logging
import time
import zlib
from collections import deque
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from typing import Any, Final

from asyncua import Server, ua

from server.core.machine.decisions import DecisionNote
from server.core.machine.transitions import Event, State
from server.opcua import packml_model as model
from server.opcua import tags
from server.opcua.address_space import (
    ALARM_EXTENT,
    MACHINES,
    NULL_TIME,
    CellNodes,
    data_value,
)
from server.opcua.nodes import nid
from server.opcua.packml import SETTLES_IN, PackMLState, PackMLTracker, UnitMode
from server.opcua.packml_types import STATES_TIMES

log = logging.getLogger(__name__)

# Admin's alarm Category, from the cell's classification of a fault.
CATEGORY: Final = {"critical": 1, "recoverable": 2, "warning": 3}
PIECE: Final = ua.EUInformation(
    NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
    UnitId=(ord("H") << 16) | (ord("8") << 8) | ord("7"),  # UNECE H87: piece
    DisplayName=ua.LocalizedText("pc"),
    Description=ua.LocalizedText("piece"),
)


def alarm_id(code: str) -> int:
    """A fault code's number for PackML's Int32 ID: CRC-32 of the code, 31 bits, so the
    same code has the same number on every cell and at every start."""
    return zlib.crc32(code.encode()) & 0x7FFFFFFF


def alarm(record: Mapping[str, Any], active: bool = True) -> Any:
    """A fault or warning of the cell as a PackMLAlarmDataType."""
    made = ua.PackMLAlarmDataType()  # type: ignore[attr-defined]
    code = str(record.get("code") or "")
    made.ID, made.Value = (alarm_id(code) if code else 0), 0
    component = record.get("component")
    made.Message = f"{code}: {record.get('message') or ''}" if code else ""
    if code and component:
        made.Message += f" ({component})"
    made.Category = CATEGORY.get(str(record.get("classification") or "critical"), 1) if code else 0
    stamp = record.get("time")
    timed = isinstance(stamp, float | int)
    made.DateTime = datetime.fromtimestamp(stamp, UTC) if timed else NULL_TIME  # type: ignore[arg-type]
    made.AckDateTime = NULL_TIME  # acknowledged: the alarms' conditions say so, not this
    made.Trigger = active
    return made


def count(name: str, value: int) -> Any:
    made = ua.PackMLCountDataType()  # type: ignore[attr-defined]
    made.ID, made.Name, made.Unit, made.Count, made.AccCount = 1, name, PIECE, value, value
    return made


class PackMLFeed:
    """The PackML tags of one cell's address space."""

    def __init__(
        self, server: Server, nodes: CellNodes, clock: Callable[[], float] = time.time
    ) -> None:
        self.server = server
        self.nodes = nodes
        self.clock = clock
        self.tracker = PackMLTracker(PackMLState.IDLE)
        self._lock = asyncio.Lock()
        self._tasks: set[asyncio.Task[None]] = set()
        self._started = clock()
        self._since = self._started  # when the current state was entered
        self._mode_since = self._started
        self._state_totals: dict[tuple[int, int], float] = {}
        self._shown = (UnitMode.PRODUCE, PackMLState.IDLE)  # the mode and state written last
        self.warnings: deque[dict[str, Any]] = deque(maxlen=ALARM_EXTENT)
        self._written: dict[str, object] = {}  # each tag's value as last written

    # --- what the cell says ------------------------------------------------------------

    async def begin(self, state: State, at: float | None) -> None:
        """Start where the cell is (the server's start, or a catch-up after a drop)."""
        self.tracker = PackMLTracker.of(state)
        await self._publish([self.tracker.state], at, force=True)

    def decided(self, note: DecisionNote) -> None:
        """The worker's verdict (server/core/worker/decisions.py): the acting state, written
        by a task of its own so the worker goes on at once."""
        tracker = self.tracker
        if note.verdict == "accepted" and note.target is not None:
            entered = tracker.accepted(note.state, note.event, note.target)
        elif note.verdict == "probing":
            entered = tracker.probing(note.state, note.event)
        else:
            entered = tracker.refused(note.state, note.event)
        if entered:
            self._spawn(self._publish(entered, note.at))

    async def settled(self, data: Mapping[str, Any], at: float | None) -> None:
        """A state_changed message: the settled state."""
        old, new = State(data["old_state"]), State(data["new_state"])
        entered = self.tracker.settled(old, new, Event(data["event"]))
        await self._publish(entered, at)

    async def progressed(self, state: State, at: float | None) -> None:
        """The running operation reported a step."""
        await self._publish(self.tracker.progressed(state), at)

    async def resetting(self) -> None:
        """PackML's Reset was accepted: Resetting while the devices are probed."""
        await self._publish(self.tracker.resetting(), self.clock())

    async def reset_done(self) -> None:
        await self._publish(self.tracker.reset_done(), self.clock())

    def warned(self, record: Mapping[str, Any]) -> None:
        """A warning of the cell (an `alert` message): the newest first in Admin.Warning."""
        self.warnings.appendleft(dict(record, time=record.get("time") or self.clock()))

    def warning_cleared(self, record: Mapping[str, Any]) -> None:
        """A warning's cause has gone (an `alert_cleared` message): out of Admin.Warning."""
        kept = [w for w in self.warnings if w.get("code") != record.get("code")]
        self.warnings.clear()
        self.warnings.extend(kept)

    async def stop(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    # --- writing -------------------------------------------------------------------------

    def _spawn(self, work: Any) -> None:
        task = asyncio.get_running_loop().create_task(work, name="opcua-packml")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _publish(
        self, entered: list[PackMLState], at: float | None, force: bool = False
    ) -> None:
        if not entered and not force:
            return
        async with self._lock:
            try:
                for state in entered:
                    await self._enter(state, at)
                if self.tracker.skipped:
                    log.warning(
                        "OPC UA: %d PackML state change(s) were not the standard's transitions",
                        self.tracker.skipped,
                    )
                    self.tracker.skipped = 0
            except Exception:  # a tag not written must not end the feed
                log.exception("OPC UA: could not write the PackML state")

    async def _enter(self, state: PackMLState, at: float | None) -> None:
        now = at if at is not None else self.clock()
        self._account(now)
        self._shown = (self.tracker.mode, state)
        path = model.path_of(state)
        packml = self.nodes.packml
        for depth, (machine, _) in enumerate(MACHINES):
            node = path[depth] if depth < len(path) else None
            prefix = f"{machine}.CurrentState"
            text = ua.LocalizedText(node.name if node is not None else "")
            await self._write(prefix, text, at)
            node_id = nid(node.node_id, packml) if node is not None else ua.NodeId()
            await self._write(f"{prefix}.Id", node_id, at)
            await self._write(f"{prefix}.Number", node.number if node is not None else 0, at)
        await self._write("Status.StateCurrent", int(state), at)
        await self._write("Status.StateRequested", int(SETTLES_IN.get(state, state)), at)
        await self._write("Status.UnitModeCurrent", int(self.tracker.mode), at)
        await self._write("Status.CurMachSpeed", 1.0 if state is PackMLState.EXECUTE else 0.0, at)
        await self.write_times(now)

    def _account(self, now: float) -> None:
        """Add the time spent in the state and mode being left to their totals."""
        key = (int(self._shown[0]), int(self._shown[1]))
        self._state_totals[key] = self._state_totals.get(key, 0.0) + (now - self._since)
        self._since = now

    async def write_times(self, now: float | None = None) -> None:
        """Admin's time arrays: [mode][state] and [mode], whole seconds."""
        now = now if now is not None else self.clock()
        modes, states = len(model.UnitMode), STATES_TIMES
        mode, state = int(self._shown[0]), int(self._shown[1])
        current = [0] * (modes * states)
        current[mode * states + state] = int(now - self._since)
        cumulative = [0] * (modes * states)
        for (m, s), seconds in self._state_totals.items():
            cumulative[m * states + s] = int(seconds)
        cumulative[mode * states + state] += int(now - self._since)
        mode_current = [0] * modes
        mode_current[mode] = int(sum(current))
        mode_cumulative = [0] * modes
        for index in range(len(cumulative)):
            mode_cumulative[index // states] += cumulative[index]
        await self._write("Admin.StateCurrentTime", current, None)
        await self._write("Admin.StateCumulativeTime", cumulative, None)
        await self._write("Admin.ModeCurrentTime", mode_current, None)
        await self._write("Admin.ModeCumulativeTime", mode_cumulative, None)
        await self._write("Admin.AccTimeSinceReset", int(now - self._started), None)

    async def write_admin(
        self, snapshot: Mapping[str, Any], counts: Mapping[str, int], at: float | None
    ) -> None:
        """Admin's stop reason, alarms, warnings and counts from the cell's snapshot and KPIs."""
        reason = snapshot.get("stop_reason")
        error = snapshot.get("error")
        active = snapshot.get("state") == State.ERROR.value
        await self._write("Admin.StopReason", alarm(reason or {}, active and bool(reason)), at)
        alarms = []
        if active and reason:
            alarms.append(alarm(reason))
            if error and error.get("event_id") != reason.get("event_id"):
                alarms.append(alarm(error))
        await self._write("Admin.Alarm", alarms[:ALARM_EXTENT], at)
        await self._write("Admin.Warning", [alarm(w) for w in self.warnings], at)
        for name, value in counts.items():
            label = "parts processed" if name == "ProdProcessedCount" else "parts defective"
            await self._write(f"Admin.{name}", [count(label, value)], None)

    async def write_constants(self, cell_id: str) -> None:
        """What never changes while the server runs: extents, speeds, flags, identity."""
        for name in ("AlarmExtent", "WarningExtent"):
            await self._write(f"Admin.{name}", ALARM_EXTENT, None)
        await self._write("Admin.StopReasonExtent", 1, None)
        await self._write("Admin.MachDesignSpeed", 1.0, None)
        await self._write("Status.MachSpeed", 1.0, None)
        await self._write("Status.EquipmentBlocked", False, None)
        await self._write("Status.EquipmentStarved", False, None)
        await self._write("PackMLVersion", model.VERSION, None)
        await self._write("TagID", cell_id, None)

    async def _write(self, path: str, value: object, at: float | None) -> None:
        """Write `path` if its value changed, as the interface writes its tags: about half
        of a state's twenty tags keep their value from one state to the next (the
        machines above the one that changed, the mode, the speeds)."""
        if path in self._written and tags.same(self._written[path], value):
            return
        self._written[path] = value
        nodes = self.nodes
        kind = nodes.types[path]
        await self.server.write_attribute_value(
            nodes.variables[path], data_value(kind, value, at, nodes.dimensions.get(path))
        )

"""CellView: the one read interface to the running cell.

The API's queries, the WebSocket hub, the metrics and the in-process façade
read the cell through this view, never through the worker's attributes, so
the worker can change its insides without touching them (as httpx's Client
never shows its connection pool). Everything here reads; nothing changes the
machine.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from server.core.machine.decide import RESET_UNDER_WAY, precondition
from server.core.machine.engine import available_commands, check
from server.core.machine.events import payload_of
from server.core.machine.transitions import COMMANDS, Command, State
from server.core.operations.frames import Frame

if TYPE_CHECKING:
    from server.core.worker.runs import RunEnded
    from server.core.worker.worker import Worker

SNAPSHOT_HISTORY = 20  # transitions in a WebSocket snapshot


class CellView:
    """Read-only views of the machine, its run, its devices and its figures."""

    def __init__(self, worker: Worker) -> None:
        self._worker = worker
        self._ctx = worker.ctx

    @property
    def state(self) -> State:
        return self._ctx.state

    @property
    def since(self) -> float:
        """When the current state was entered (Unix time)."""
        return self._ctx.since

    def snapshot(self) -> dict[str, Any]:
        """The state as GET /state and the WebSocket snapshot show it (taken at every change
        of state: the states' names by `str()`, a StrEnum's value without the enum's
        Python-level `value` property)."""
        ctx = self._ctx
        now = self._worker.clock.time()
        operation = None
        if ctx.operation is not None:
            operation = {
                "name": ctx.operation.name,
                "run_id": ctx.operation.run_id,
                "progress": ctx.operation.progress or None,
            }
        return {
            "state": str(ctx.state),
            "previous_state": str(ctx.previous_state) if ctx.previous_state else None,
            "since": ctx.since,
            "time_in_state": round(now - ctx.since, 3),
            "operation": operation,
            "error": ctx.error.as_dict() if ctx.error else None,
            "stop_reason": ctx.stop_reason.as_dict() if ctx.stop_reason else None,
            "available_commands": self._available_commands(),
            "operation_result": ctx.operation_result,
        }

    def live_snapshot(self) -> dict[str, Any]:
        """The snapshot a WebSocket client gets first: the state, its context, recent history."""
        ctx = self._ctx
        return {
            **self.snapshot(),
            "context": {
                "operation_data": ctx.operation_data,
                "error_message": ctx.error_message,
                "operation_result": ctx.operation_result,
            },
            "history": [r.as_dict() for r in list(ctx.history)[-SNAPSHOT_HISTORY:]],
        }

    def current_run(self) -> dict[str, Any] | None:
        """The operation running now: name, run id and the workpiece it sprays, if named.

        The workpiece is the one the run's progress last named (contour matching
        sprays several in turn), else the one the start asked for.
        """
        running = self._ctx.operation
        if running is None:
            return None
        workpiece = running.progress.get("workpiece_id") or running.params.get("workpiece_id")
        return {"name": running.name, "run_id": running.run_id, "workpiece_id": workpiece}

    def _available_commands(self) -> list[str]:
        commands = available_commands(self._ctx.state, self._worker.facts())
        if self._worker.reset_probes.under_way:  # one reset is probed at a time
            commands = [name for name in commands if name != Command.RESET]
        return commands

    def allowed(self, command: Command) -> tuple[bool, str]:
        """Whether `command` (with default parameters) would be accepted now, and why not.

        The same checks as the worker's, in the same order: the state (and its
        guards), then what the command needs besides (`decide.precondition`).
        """
        event = COMMANDS[command]
        if command is Command.RESET and self._worker.reset_probes.under_way:
            return False, f"reset is refused: {RESET_UNDER_WAY}"
        allowed, reason = check(self._ctx.state, event, self._worker.facts())
        if not allowed:
            return allowed, reason
        payload = payload_of(event, None)
        facts = self._worker.decision_facts(event, payload)
        unmet = precondition(event, payload, facts, self._worker.settings)
        if unmet is not None:
            return False, f"{command} is refused: {unmet.message}"
        return True, reason

    @property
    def robot_moving(self) -> bool:
        """Whether a move outside operations (home, a jog) is under way."""
        return self._worker.activities.moving

    @property
    def robot_moves_started(self) -> int:
        """How many such moves have begun: a pose read across a change of it is stale."""
        return self._worker.activities.moves_started

    @property
    def error_message(self) -> str | None:
        return self._ctx.error_message

    @property
    def operation_result(self) -> dict[str, Any] | None:
        """What the last operation that completed returned."""
        return self._ctx.operation_result

    def health(self) -> dict[str, Any]:
        """Each device's link, last round-trip and last error; the worker's figures."""
        worker = self._worker
        devices = worker.devices.health()
        return {
            "status": "ok" if all(d["connected"] for d in devices.values()) else "degraded",
            "state": self._ctx.state.value,
            "devices": devices,
            "worker": self.performance(),
            "journal": worker.recorder.journal_health(),
        }

    def performance(self) -> dict[str, Any]:
        """Events processed and refused, processing times, queue depth."""
        return self._worker.stats.snapshot(len(self._worker.queue))

    def trajectory(self) -> dict[str, Any] | None:
        """The planned path of the current or last run, with the waypoint reached."""
        plan = self._worker.runs.trajectory
        if plan is None:
            return None
        running = self._ctx.operation
        current = running is not None and running.run_id == plan["run_id"]
        reached = running.progress.get("waypoint") if running is not None and current else None
        return {**plan, "running": current, "waypoint": reached}

    def is_current_run(self, run_id: str) -> bool:
        """Whether `run_id` is the operation running now (started, not yet ended)."""
        return self._worker.runs.is_current(run_id)

    def latest_frame(self) -> Frame | None:
        """The last frame an operation measured on."""
        return self._worker.runs.frames.latest

    def frame_jpeg(self, frame: Frame) -> bytes:
        """`frame` as JPEG (made once per frame; call off the event loop)."""
        return self._worker.runs.frames.jpeg(frame)

    def on_event_decided(self, listener: Callable[[float], None]) -> None:
        """Call `listener(seconds)` after each event is decided (e.g. a histogram)."""
        self._worker.stats.listeners.append(listener)

    def on_run_started(self, listener: Callable[[str], None]) -> None:
        """Call `listener(operation)` as an operation starts, before its first step (in the
        worker: never block)."""
        self._worker.runs.start_listeners.append(listener)

    def on_run_ended(self, listener: Callable[[RunEnded], None]) -> None:
        """Call `listener(ended)` when an operation ends (in the worker: never block)."""
        self._worker.runs.listeners.append(listener)

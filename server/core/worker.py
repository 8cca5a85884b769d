"""The worker: the one consumer of the event queue and the only code that changes state.

It takes one envelope at a time, asks the pure engine for a decision, and acts
on it in a fixed order:

1. exit:  when the running operation ends, halt safely (valve first) and
          cancel the operation task; leaving IDLE cancels the homing move;
          a pause closes the operation's gate;
2. change the state, append to the history, publish `state_changed`;
3. entry: ERROR records the fault and halts; IDLE clears the operation data
          and sends the robot to its safe position; an operational state
          starts its operation; a resume opens the gate again.

Then the sender's future gets the outcome, so an HTTP command answers once the
worker has decided. Operations and devices talk back only by posting events
(OPERATION_COMPLETED, OPERATION_FAILED, ERROR_OCCURRED), which keeps every
change of state in this one loop.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from server.config import Settings
from server.core.bus import Bus
from server.core.context import (
    FaultRecord,
    MachineContext,
    ProcessingStats,
    RunningOperation,
    TransitionRecord,
)
from server.core.devices import CellDevices
from server.core.engine import REQUIRED_DEVICES, Decision, Facts, available_commands, step
from server.core.event_queue import Envelope, EventQueue, Priority
from server.core.faults import classify, recommended_action
from server.core.frames import LatestFrame
from server.core.journal import Journal, Record
from server.core.operations.base import Operation, OperationContext, PauseGate
from server.core.snapshot import SnapshotFile
from server.core.supervision import RunOutcome, supervise
from server.core.transitions import (
    OPERATION_OF_STATE,
    READINESS_EVENTS,
    Event,
    State,
    event_label,
)
from server.drivers.base import DeviceFault, Pose
from server.errors import EventQueueFull, TransitionNotAllowed, WorkerStopped
from server.logging_setup import current_event_id
from server.storage import CellStores

log = logging.getLogger(__name__)

COMPLETION_EVENTS = frozenset({Event.OPERATION_COMPLETED, Event.OPERATION_FAILED})
JOURNAL_BACKLOG_LIMIT = 10_000
SLOW_OPERATION_SHARE = 0.8  # of processing_timeout: a run this slow is warned of
OVERTAKEN = "overtaken by an emergency stop while it was being decided; nothing was changed"
OPERATION_OUTCOME = {
    Event.OPERATION_COMPLETED: "completed",
    Event.CANCEL_REQUESTED: "cancelled",
}


@dataclass(frozen=True, slots=True)
class Outcome:
    """The worker's answer to one event."""

    accepted: bool
    event_id: str
    event: Event
    state: State
    message: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "accepted": self.accepted,
            "event_id": self.event_id,
            "event": self.event.value,
            "state": self.state.value,
            "message": self.message,
        }


class Worker:
    """Drains the event queue and runs the machine's actions."""

    def __init__(
        self,
        settings: Settings,
        devices: CellDevices,
        operations: dict[str, Operation],
        bus: Bus,
        stores: CellStores,
        *,
        journal: Journal | None = None,
        snapshot_file: SnapshotFile | None = None,
        interruption: str | None = None,
    ) -> None:
        self.settings = settings
        self.devices = devices
        self.operations = operations
        self.bus = bus
        self.stores = stores
        self.journal = journal
        self.snapshot_file = snapshot_file
        self.interruption = interruption  # why the last run of the server ended mid-operation
        self.ctx = MachineContext(history_size=settings.history_size)
        self.queue = EventQueue(settings.event_queue_size)
        self.stats = ProcessingStats(settings.performance_history_size)
        self.trajectory: dict[str, Any] | None = None  # the plan of the current or last run
        self.frames = LatestFrame()  # the last frame an operation measured on, for the HMI
        self._ready: set[str] = set()
        self._boot = secrets.token_hex(3)
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._op_task: asyncio.Task[None] | None = None
        self._gate: PauseGate | None = None
        self._activity: asyncio.Task[None] | None = None  # start-up or homing
        self._error_timer: asyncio.Task[None] | None = None
        self._estops = 0  # e-stops requested so far; see _overtaken
        self._records: list[Record] = []  # journal records of the event being handled
        # Called with (kind, outcome, seconds) when an operation ends, e.g. by metrics.
        self.operation_listeners: list[Callable[[str, str, float], None]] = []

    # --- lifecycle ---------------------------------------------------------

    async def start(self) -> None:
        """Enter INITIALIZING, connect the devices, and begin draining the queue."""
        self._loop = asyncio.get_running_loop()
        self.devices.set_fault_listener(self.report_fault)
        self.ctx.since = time.time()
        self._task = asyncio.create_task(self._run(), name="cell-worker")
        self._activity = asyncio.create_task(self._bring_up_devices(), name="device-start-up")

    async def stop(self) -> None:
        """Stop draining; every waiting sender gets WorkerStopped, never a hang."""
        tasks = (self._task, self._op_task, self._activity, self._error_timer)
        for task in tasks:
            if task is not None:
                task.cancel()
        for task in tasks:
            if task is not None:
                await asyncio.gather(task, return_exceptions=True)
        for envelope in self.queue.drain():
            if envelope.future is not None and not envelope.future.done():
                envelope.future.set_exception(WorkerStopped("the server is shutting down"))
        self.devices.set_fault_listener(None)

    # --- posting events ----------------------------------------------------

    def new_event_id(self) -> str:
        return f"{self._boot}-{next(self._ids):06d}"

    def submit(
        self,
        event: Event,
        *,
        source: str,
        data: dict[str, Any] | None = None,
        priority: Priority = Priority.REQUEST,
        bounded: bool = True,
    ) -> Envelope:
        """Queue an event (loop thread only). Raises EventQueueFull when `bounded` and full."""
        loop = self._loop or asyncio.get_running_loop()
        if bounded and self.journal is not None and self.journal.backlog > JOURNAL_BACKLOG_LIMIT:
            raise EventQueueFull(self.queue.capacity)  # the disk is behind: refuse, never drop
        envelope = Envelope(
            event_id=self.new_event_id(),
            event=event,
            source=source,
            data=data or {},
            priority=priority,
            future=loop.create_future(),
        )
        self.queue.put(envelope, bounded=bounded)
        return envelope

    async def request(
        self, event: Event, *, source: str, data: dict[str, Any] | None = None
    ) -> Outcome:
        """Queue a request and wait for the worker's decision."""
        envelope = self.submit(event, source=source, data=data)
        assert envelope.future is not None
        return await envelope.future

    async def emergency_stop(self, *, source: str, data: dict[str, Any] | None = None) -> Outcome:
        """Halt the devices now, without queueing, then have the machine go to ERROR.

        The valve-close and robot-stop commands leave before the event is even
        queued; the EMERGENCY_STOP event then overtakes everything waiting.
        """
        self._estops += 1  # anything being decided now must not undo this stop
        halt = self.devices.start_halt(self.settings.emergency_stop_timeout)
        envelope = self.submit(
            Event.EMERGENCY_STOP,
            source=source,
            data=data or {},
            priority=Priority.EMERGENCY,
            bounded=False,
        )
        assert envelope.future is not None
        report = await asyncio.shield(halt)
        outcome: Outcome = await envelope.future
        if report.errors:
            detail = "; ".join(report.errors)
            return Outcome(
                outcome.accepted,
                outcome.event_id,
                outcome.event,
                outcome.state,
                f"{outcome.message}; halt incomplete: {detail}",
            )
        return outcome

    def report_fault(self, fault: DeviceFault) -> None:
        """Fault listener for the drivers; safe to call from any thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(self._post_fault, fault)

    def _post_fault(self, fault: DeviceFault) -> None:
        envelope = self.submit(
            Event.ERROR_OCCURRED,
            source=fault.device,
            data={"code": fault.code, "message": fault.message, "component": fault.device},
            priority=Priority.FAULT,
            bounded=False,
        )
        log.error(
            "device fault: %s %s: %s (event %s)",
            fault.device,
            fault.code,
            fault.message,
            envelope.event_id,
        )

    # --- queries -----------------------------------------------------------

    def facts(self) -> Facts:
        """Guard facts from what is known without asking the devices (a reset probes them)."""
        known: list[str] = []
        for name, device in self.devices.by_name().items():
            health = device.health
            known.extend(health.active_faults if health.connected else (f"{name}: not connected",))
        return Facts(ready_devices=frozenset(self._ready), active_faults=tuple(known))

    def snapshot(self) -> dict[str, Any]:
        """The state as GET /state and the WebSocket snapshot show it."""
        ctx = self.ctx
        now = time.time()
        operation = None
        if ctx.operation is not None:
            operation = {
                "name": ctx.operation.name,
                "run_id": ctx.operation.run_id,
                "progress": ctx.operation.progress or None,
            }
        return {
            "state": ctx.state.value,
            "previous_state": ctx.previous_state.value if ctx.previous_state else None,
            "since": ctx.since,
            "time_in_state": round(now - ctx.since, 3),
            "operation": operation,
            "error": ctx.error.as_dict() if ctx.error else None,
            "stop_reason": ctx.stop_reason.as_dict() if ctx.stop_reason else None,
            "available_commands": available_commands(ctx.state, self.facts()),
            "operation_result": ctx.operation_result,
        }

    def performance(self) -> dict[str, Any]:
        return self.stats.snapshot(len(self.queue))

    # --- the loop ----------------------------------------------------------

    async def _run(self) -> None:
        while True:
            envelope = await self.queue.get()
            started = time.perf_counter()
            token = current_event_id.set(envelope.event_id)
            try:
                outcome = await self._handle(envelope)
            except asyncio.CancelledError:
                if envelope.future is not None and not envelope.future.done():
                    envelope.future.set_exception(WorkerStopped("the server is shutting down"))
                raise
            except Exception as exc:
                log.exception(
                    "event %s (%s) failed in the worker", envelope.event_id, envelope.event
                )
                outcome = Outcome(
                    False,
                    envelope.event_id,
                    envelope.event,
                    self.ctx.state,
                    f"internal error while handling {event_label(envelope.event)}: {exc}",
                )
            finally:
                current_event_id.reset(token)
            self.stats.record(time.perf_counter() - started, accepted=outcome.accepted)
            self._answer(envelope, outcome, self._journal_event(envelope, outcome))
            # Let the loop run between events, so a long queue of quick refusals
            # never starves the HTTP handlers (the e-stop route above all).
            await asyncio.sleep(0)

    def _journal_event(self, envelope: Envelope, outcome: Outcome) -> asyncio.Future[None] | None:
        """Hand the event and what it caused to the journal; the future marks it durable."""
        records, self._records = self._records, []
        if self.journal is None:
            return None
        records.insert(
            0,
            Journal.event(
                envelope.event_id,
                envelope.timestamp,
                envelope.event.value,
                envelope.source,
                envelope.data,
                "accepted" if outcome.accepted else "refused",
                outcome.message,
                outcome.state.value,
            ),
        )
        return self.journal.append(records)

    def _journal_failed(self, problem: str) -> None:
        """The record is not on disk: stop the cell, once, and say so."""
        if self.ctx.stop_reason is not None and self.ctx.stop_reason.code == "JOURNAL_WRITE_FAILED":
            return
        self._post_fault(
            DeviceFault(
                "journal",
                "JOURNAL_WRITE_FAILED",
                f"the journal could not be written ({problem}); records may "
                "be missing: check the disk under the data directory",
            )
        )

    def _answer(
        self, envelope: Envelope, outcome: Outcome, durable: asyncio.Future[None] | None
    ) -> None:
        """Answer the sender once the event is on disk (at once without a journal)."""
        future = envelope.future
        if future is None or future.done():
            return
        if durable is None:
            future.set_result(outcome)
            return

        def settle(written: asyncio.Future[None]) -> None:
            if future.done():
                return
            if written.cancelled() or written.exception() is not None:
                problem = "cancelled" if written.cancelled() else written.exception()
                log.critical("event %s decided but not journaled: %s", outcome.event_id, problem)
                self._journal_failed(str(problem))
                future.set_result(
                    Outcome(
                        outcome.accepted,
                        outcome.event_id,
                        outcome.event,
                        outcome.state,
                        f"{outcome.message} (journal write failed: {problem})",
                    )
                )
            else:
                future.set_result(outcome)

        durable.add_done_callback(settle)

    async def _handle(self, envelope: Envelope) -> Outcome:
        event, state = envelope.event, self.ctx.state
        if event in COMPLETION_EVENTS and not self._is_current_run(envelope):
            return self._refuse(envelope, f"{event.value} of a run that already ended; ignored")
        facts = self.facts()
        estops = self._estops
        if event is Event.RESET_REQUESTED and state is State.ERROR:
            faults = await self.devices.probe_faults(self._device_timeouts())
            facts = Facts(ready_devices=facts.ready_devices, active_faults=tuple(faults))
            if self._estops != estops:
                return self._refuse(envelope, OVERTAKEN)
        try:
            decision = step(state, event, facts)
        except TransitionNotAllowed as refusal:
            return self._refuse(envelope, str(refusal))
        if not await self._apply(decision, envelope, estops):
            return self._refuse(envelope, OVERTAKEN)
        target = decision.target.value
        return Outcome(
            True,
            envelope.event_id,
            event,
            self.ctx.state,
            f"{event_label(event)} accepted: {state.value} → {target}",
        )

    def _refuse(self, envelope: Envelope, message: str) -> Outcome:
        log.info(
            "refused %s (%s) from %s: %s",
            envelope.event.value,
            envelope.event_id,
            envelope.source,
            message,
        )
        return Outcome(False, envelope.event_id, envelope.event, self.ctx.state, message)

    def _is_current_run(self, envelope: Envelope) -> bool:
        running = self.ctx.operation
        return running is not None and envelope.data.get("run_id") == running.run_id

    # --- acting on a decision ------------------------------------------------

    async def _apply(self, decision: Decision, envelope: Envelope, estops: int) -> bool:
        """Act on a decision; False (nothing changed) if an e-stop came in meanwhile."""
        source, target, event = decision.source, decision.target, decision.event
        halted = False

        # 1. exit actions
        if decision.ends_operation:
            self._journal_operation_end(envelope)
            if target is State.ERROR:
                await self._halt()  # valve first, before anything else
            await self._cancel_operation()
            # Again once the operation is gone: a valve command of its own may have
            # been on the line behind the first close.
            await self._halt()
            halted = True
        if source is State.IDLE and target is not State.IDLE:
            await self._cancel_activity()
        if target is not State.ERROR and self._estops != estops:
            return False
        if event is Event.PAUSE_REQUESTED and self._gate is not None:
            self._gate.pause()

        # 2. the state change (a fault is on record before anyone sees the new state)
        if target is State.ERROR:
            self._record_fault(envelope, target)
        if decision.changes_state:
            self._change_state(decision, envelope)

        # 3. entry actions
        if event in READINESS_EVENTS:
            self._note_ready(READINESS_EVENTS[event])
        if target is State.ERROR:
            if decision.changes_state and not halted:
                await self._halt()
        elif target is State.IDLE and decision.changes_state:
            self._enter_idle(envelope)
        if decision.starts_operation:
            self._start_operation(target, envelope)
        if event is Event.RESUME_REQUESTED and self._gate is not None:
            self._gate.resume()
        return True

    def _change_state(self, decision: Decision, envelope: Envelope) -> None:
        ctx = self.ctx
        now = time.time()
        record = TransitionRecord(
            timestamp=now,
            old_state=decision.source.value,
            new_state=decision.target.value,
            event=decision.event.value,
            event_id=envelope.event_id,
            time_in_old_state=round(now - ctx.since, 6),
        )
        ctx.history.append(record)
        ctx.previous_state, ctx.state, ctx.since = decision.source, decision.target, now
        log.info(
            "%s → %s on %s (%s, from %s)",
            record.old_state,
            record.new_state,
            record.event,
            envelope.event_id,
            envelope.source,
        )
        if self.journal is not None:
            self._records.append(Journal.transition(record.as_dict()))
        snapshot = self.snapshot()
        self._save_snapshot(snapshot)
        self.bus.publish(
            "state_changed", {**record.as_dict(), "source": envelope.source, "snapshot": snapshot}
        )
        self._watch_error_state(decision.target)

    async def _halt(self) -> None:
        report = await self.devices.safe_halt(self.settings.emergency_stop_timeout)
        for error in report.errors:
            self.bus.publish(
                "error",
                {"code": "HALT_INCOMPLETE", "message": error, "component": error.split(":", 1)[0]},
            )

    def _record_fault(self, envelope: Envelope, state: State) -> None:
        data = envelope.data
        if envelope.event is Event.EMERGENCY_STOP:
            code, message = "EMERGENCY_STOP", f"emergency stop by {envelope.source}"
            if data.get("reason"):
                message += f": {data['reason']}"
            component = envelope.source
        else:
            code = str(data.get("code", envelope.event.value))
            message = str(data.get("message", "unspecified fault"))
            component = str(data.get("component", envelope.source))
        fault = FaultRecord(
            code,
            message,
            component,
            envelope.event_id,
            time.time(),
            classify(code),
            recommended_action(code),
        )
        self.ctx.record_error(fault)
        if self.journal is not None:
            self._records.append(
                Journal.error(
                    fault.time,
                    code,
                    message,
                    component,
                    fault.classification,
                    envelope.event_id,
                    state.value,
                )
            )
        log.error(
            "fault %s from %s in %s state (%s)",
            code,
            component,
            self.ctx.state.value,
            envelope.event_id,
            extra={"error": message, "context": self._fault_context()},
        )
        self.bus.publish("error", {**fault.as_dict(), "state": state.value})

    def _fault_context(self) -> dict[str, Any]:
        """What was going on when a fault came: the operation, its run and its parameters."""
        running = self.ctx.operation
        if running is None:
            return {"operation": None}
        context: dict[str, Any] = {"operation": running.name, "run_id": running.run_id}
        context.update(running.params)
        progress = running.progress
        if "waypoint" in progress:
            context["waypoint"] = f"{progress['waypoint']} of {progress.get('of', '?')}"
        return context

    def _enter_idle(self, envelope: Envelope) -> None:
        ctx = self.ctx
        if envelope.event is Event.OPERATION_COMPLETED:
            ctx.operation_result = envelope.data.get("result")
        ctx.operation_data = {}
        if envelope.event is Event.RESET_REQUESTED:
            ctx.clear_error()
        if self._activity is not None and not self._activity.done():
            self._activity.cancel()  # e.g. a start-up still connecting after an early fault
        self._activity = asyncio.create_task(self._go_to_safe_position(), name="homing")

    def _note_ready(self, device: str) -> None:
        self._ready.add(device)
        if self._ready >= REQUIRED_DEVICES and self.ctx.state is State.INITIALIZING:
            self.submit(Event.SYSTEM_READY, source="system", bounded=False)

    # --- operations ----------------------------------------------------------

    def _start_operation(self, state: State, envelope: Envelope) -> None:
        name = OPERATION_OF_STATE[state]
        run_id = envelope.event_id
        self._gate = PauseGate()
        self.ctx.operation = RunningOperation(name, run_id, time.time(), dict(envelope.data))
        if self.journal is not None:
            self._records.append(
                Journal.operation_started(run_id, name, time.time(), dict(envelope.data))
            )
        self.ctx.operation_data = dict(envelope.data)
        self.ctx.operation_result = None
        op_ctx = OperationContext(
            robot=self.devices.robot,
            glue=self.devices.glue,
            camera=self.devices.camera,
            settings=self.settings,
            stores=self.stores,
            params=dict(envelope.data),
            report=lambda progress: self._on_progress(run_id, progress),
            gate=self._gate,
            run_id=run_id,
            operation=name,
            frames=self.frames,
        )
        self._op_task = asyncio.create_task(
            self._supervise(self.operations[name], op_ctx), name=f"operation-{name}"
        )

    async def _supervise(self, operation: Operation, op_ctx: OperationContext) -> None:
        """Run one operation (budget and retries in supervision.py); post its outcome."""
        run_id = op_ctx.run_id

        def on_retry(attempt: int, code: str, succeeded: bool) -> None:
            if self.journal is not None:
                self.journal.append(
                    [Journal.recovery(time.time(), run_id, code, attempt, succeeded)], durable=False
                )
            running = self.ctx.operation
            self.bus.publish(
                "progress",
                {
                    "operation": running.name if running else "",
                    "run_id": run_id,
                    "recovery_attempt": attempt,
                    "recovered": succeeded,
                    "cause": code,
                },
            )

        outcome: RunOutcome = await supervise(operation, op_ctx, self.settings, on_retry)
        if outcome.succeeded:
            self.submit(
                Event.OPERATION_COMPLETED,
                source="operation",
                data={"run_id": run_id, "result": outcome.result},
                bounded=False,
            )
        else:
            self._post_failure(run_id, outcome.code, outcome.message, outcome.component)

    def _post_failure(self, run_id: str, code: str, message: str, component: str) -> None:
        self.submit(
            Event.OPERATION_FAILED,
            source="operation",
            data={"run_id": run_id, "code": code, "message": message, "component": component},
            priority=Priority.FAULT,
            bounded=False,
        )

    def _on_progress(self, run_id: str, progress: dict[str, Any]) -> None:
        running = self.ctx.operation
        if running is None or running.run_id != run_id:
            return
        update = dict(progress)
        if "planned_path" in update:
            self.trajectory = {
                "run_id": run_id,
                "planned_path": update.pop("planned_path"),
                "workpieces": update.pop("workpieces", []),
            }
        running.progress.update(update)
        if self.journal is not None:
            self.journal.append(
                [Journal.operation_progress(run_id, running.progress)], durable=False
            )
        self.bus.publish(
            "progress",
            {
                "operation": running.name,
                "run_id": run_id,
                "state": self.ctx.state.value,
                **running.progress,
            },
        )

    async def _cancel_operation(self) -> None:
        task, self._op_task = self._op_task, None
        if self._gate is not None:
            self._gate.resume()  # a held operation must see the cancellation, not the gate
        self._gate = None
        self.ctx.operation = None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=self.settings.emergency_stop_timeout)

    # --- activities: start-up and homing -----------------------------------

    async def _cancel_activity(self) -> None:
        task, self._activity = self._activity, None
        if task is not None and not task.done():
            task.cancel()
            # Wait for the robot's stop to be answered, so it cannot stop the next move.
            await asyncio.wait({task}, timeout=self.settings.emergency_stop_timeout)

    def _device_timeouts(self) -> dict[str, float]:
        return {
            "robot": self.settings.robot_communication_timeout,
            "glue": self.settings.glue_system_timeout,
            "camera": self.settings.vision_processing_timeout,
        }

    async def _bring_up_devices(self) -> None:
        """Connect every device, close the valve and stop the robot, then report.

        The halt comes first on every start: whatever the last run left behind,
        nothing sprays or moves until the machine says so. After an interruption
        the fault is posted before any READY, so the cell cannot reach IDLE by itself.
        """
        timeouts = self._device_timeouts()
        results = await asyncio.gather(
            *(self.devices.connect(name, timeouts[name]) for name in timeouts),
            return_exceptions=True,
        )
        await self._halt()
        if self.interruption is not None:
            self._post_fault(DeviceFault("system", "INTERRUPTED", self.interruption))
        ready_event = {device: event for event, device in READINESS_EVENTS.items()}
        for name, result in zip(timeouts, results, strict=True):
            if isinstance(result, asyncio.CancelledError):
                raise result
            if isinstance(result, BaseException):
                reason = "no answer" if isinstance(result, TimeoutError) else str(result)
                self._post_fault(
                    DeviceFault(
                        name,
                        "DEVICE_UNAVAILABLE",
                        f"{name} did not come up within {timeouts[name]:g} s: {reason}",
                    )
                )
            else:
                self.submit(ready_event[name], source=name, bounded=False)

    async def _go_to_safe_position(self) -> None:
        settings = self.settings
        try:
            await asyncio.wait_for(
                self.devices.robot.move_linear(
                    Pose.from_sequence(settings.safe_position),
                    settings.travel_speed_mm_s,
                    settings.acceleration_mm_s2,
                ),
                settings.safe_position_timeout,
            )
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            reason = "no answer in time" if isinstance(exc, TimeoutError) else str(exc)
            self._post_fault(
                DeviceFault(
                    "robot",
                    "SAFE_POSITION_FAILED",
                    f"robot could not reach its safe position: {reason}",
                )
            )

    # --- records beyond the state: operation ends, snapshot, ERROR watch ---------

    def _journal_operation_end(self, envelope: Envelope) -> None:
        running = self.ctx.operation
        if running is None:
            return
        outcome = OPERATION_OUTCOME.get(envelope.event, "failed")
        for listener in self.operation_listeners:
            listener(running.name, outcome, time.time() - running.started_at)
        if outcome == "completed":
            self._warn_of_completed(running, envelope.data.get("result"))
        if self.journal is None:
            return
        error = None if outcome != "failed" else str(envelope.data.get("message", envelope.event))
        workpieces = 0
        if (
            running.name == "trajectory"
            and self.trajectory is not None
            and (self.trajectory["run_id"] == running.run_id)
        ):
            workpieces = len(self.trajectory["workpieces"])
        self._records.append(
            Journal.operation_ended(
                running.run_id, time.time(), outcome, envelope.data.get("result"), error, workpieces
            )
        )

    def _save_snapshot(self, snapshot: dict[str, Any]) -> None:
        if self.snapshot_file is None:
            return
        running = self.ctx.operation
        self.snapshot_file.save(
            {
                **snapshot,
                "operation": running.as_dict() if running is not None else None,
                "saved_at": time.time(),
            }
        )

    def _watch_error_state(self, state: State) -> None:
        """Raise an alert when the cell stays in ERROR longer than error_state_timeout."""
        if self._error_timer is not None:
            self._error_timer.cancel()
            self._error_timer = None
        if state is State.ERROR:
            self._error_timer = asyncio.create_task(
                self._alert_after_timeout(), name="error-state-alert"
            )

    async def _alert_after_timeout(self) -> None:
        timeout = self.settings.error_state_timeout
        await asyncio.sleep(timeout)
        reason = self.ctx.stop_reason.message if self.ctx.stop_reason else "unknown"
        message = f"the cell has been in ERROR for {timeout:g} s (first fault: {reason})"
        self._warn("ERROR_STATE_TIMEOUT", message, "system")

    def _warn_of_completed(self, running: RunningOperation, result: Any) -> None:
        """Warnings of a run that succeeded: it came close to its budget, or it said so.

        Why: a cell whose operations creep towards processing_timeout, or whose
        calibration error creeps towards its limit, is about to start failing;
        the technician should hear it while production still runs.
        """
        budget = self.settings.processing_timeout
        paused = self._gate.paused_seconds() if self._gate is not None else 0.0
        took = time.time() - running.started_at - paused
        if took > SLOW_OPERATION_SHARE * budget:
            self._warn(
                "SLOW_OPERATION",
                f"{running.name} took {took:.1f} s of its {budget:g} s budget "
                "(processing_timeout): check device speeds and lighting before runs time out",
                running.name,
            )
        warnings = result.get("warnings", []) if isinstance(result, dict) else []
        for warning in warnings:
            self._warn(str(warning.get("code")), str(warning.get("message")), running.name)

    def _warn(self, code: str, message: str, component: str) -> None:
        """A warning-class condition: logged, journaled, pushed on /ws; the cell runs on."""
        log.warning("warning %s from %s: %s", code, component, message)
        state = self.ctx.state.value
        self.bus.publish(
            "alert",
            {
                "code": code,
                "message": message,
                "component": component,
                "classification": "warning",
                "state": state,
            },
        )
        if self.journal is not None:
            event_id = current_event_id.get() or ""
            self.journal.append(
                [Journal.error(time.time(), code, message, component, "warning", event_id, state)],
                durable=False,
            )

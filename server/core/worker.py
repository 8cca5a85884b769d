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
from server.core.operations.base import Operation, OperationContext, PauseGate
from server.core.transitions import (
    OPERATION_OF_STATE,
    READINESS_EVENTS,
    Event,
    State,
    event_label,
)
from server.drivers.base import DeviceFault, Pose
from server.errors import DeviceError, OperationError, TransitionNotAllowed, WorkerStopped
from server.storage import CellStores

log = logging.getLogger(__name__)

COMPLETION_EVENTS = frozenset({Event.OPERATION_COMPLETED, Event.OPERATION_FAILED})


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
    ) -> None:
        self.settings = settings
        self.devices = devices
        self.operations = operations
        self.bus = bus
        self.stores = stores
        self.ctx = MachineContext(history_size=settings.history_size)
        self.queue = EventQueue(settings.event_queue_size)
        self.stats = ProcessingStats(settings.performance_history_size)
        self.trajectory: dict[str, Any] | None = None  # the plan of the current or last run
        self._ready: set[str] = set()
        self._boot = secrets.token_hex(3)
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._op_task: asyncio.Task[None] | None = None
        self._gate: PauseGate | None = None
        self._activity: asyncio.Task[None] | None = None  # start-up or homing

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
        for task in (self._task, self._op_task, self._activity):
            if task is not None:
                task.cancel()
        for task in (self._task, self._op_task, self._activity):
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
        halt = asyncio.ensure_future(self.devices.safe_halt(self.settings.emergency_stop_timeout))
        envelope = self.submit(
            Event.EMERGENCY_STOP,
            source=source,
            data=data or {},
            priority=Priority.EMERGENCY,
            bounded=False,
        )
        assert envelope.future is not None
        report = await halt
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
        log.error("device fault: %s %s: %s", fault.device, fault.code, fault.message)
        self.submit(
            Event.ERROR_OCCURRED,
            source=fault.device,
            data={"code": fault.code, "message": fault.message, "component": fault.device},
            priority=Priority.FAULT,
            bounded=False,
        )

    # --- queries -----------------------------------------------------------

    def facts(self) -> Facts:
        """Guard facts from what is known without asking the devices."""
        return Facts(ready_devices=frozenset(self._ready))

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
            self.stats.record(time.perf_counter() - started, accepted=outcome.accepted)
            if envelope.future is not None and not envelope.future.done():
                envelope.future.set_result(outcome)
            # Let the loop run between events, so a long queue of quick refusals
            # never starves the HTTP handlers (the e-stop route above all).
            await asyncio.sleep(0)

    async def _handle(self, envelope: Envelope) -> Outcome:
        event, state = envelope.event, self.ctx.state
        if event in COMPLETION_EVENTS and not self._is_current_run(envelope):
            return self._refuse(envelope, f"{event.value} of a run that already ended; ignored")
        facts = self.facts()
        if event is Event.RESET_REQUESTED and state is State.ERROR:
            faults = await self.devices.probe_faults(self.settings.emergency_stop_timeout)
            facts = Facts(ready_devices=facts.ready_devices, active_faults=tuple(faults))
        try:
            decision = step(state, event, facts)
        except TransitionNotAllowed as refusal:
            return self._refuse(envelope, str(refusal))
        await self._apply(decision, envelope)
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

    async def _apply(self, decision: Decision, envelope: Envelope) -> None:
        source, target, event = decision.source, decision.target, decision.event
        halted = False

        # 1. exit actions
        if decision.ends_operation:
            if target is State.ERROR:
                await self._halt()  # valve first, before anything else
                halted = True
            await self._cancel_operation()
            if not halted:
                await self._halt()
                halted = True
        if source is State.IDLE and target is not State.IDLE:
            await self._cancel_activity()
        if event is Event.PAUSE_REQUESTED and self._gate is not None:
            self._gate.pause()

        # 2. the state change
        if decision.changes_state:
            self._change_state(decision, envelope)

        # 3. entry actions
        if event in READINESS_EVENTS:
            self._note_ready(READINESS_EVENTS[event])
        if target is State.ERROR:
            self._record_fault(envelope)
            if decision.changes_state and not halted:
                await self._halt()
        elif target is State.IDLE and decision.changes_state:
            self._enter_idle(envelope)
        if decision.starts_operation:
            self._start_operation(target, envelope)
        if event is Event.RESUME_REQUESTED and self._gate is not None:
            self._gate.resume()

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
        self.bus.publish(
            "state_changed",
            {**record.as_dict(), "source": envelope.source, "snapshot": self.snapshot()},
        )

    async def _halt(self) -> None:
        report = await self.devices.safe_halt(self.settings.emergency_stop_timeout)
        for error in report.errors:
            self.bus.publish(
                "error",
                {"code": "HALT_INCOMPLETE", "message": error, "component": error.split(":", 1)[0]},
            )

    def _record_fault(self, envelope: Envelope) -> None:
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
        fault = FaultRecord(code, message, component, envelope.event_id, time.time())
        self.ctx.record_error(fault)
        log.error("fault %s from %s (%s): %s", code, component, envelope.event_id, message)
        self.bus.publish("error", {**fault.as_dict(), "state": self.ctx.state.value})

    def _enter_idle(self, envelope: Envelope) -> None:
        ctx = self.ctx
        if envelope.event is Event.OPERATION_COMPLETED:
            ctx.operation_result = envelope.data.get("result")
        ctx.operation_data = {}
        if envelope.event is Event.RESET_REQUESTED:
            ctx.clear_error()
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
        )
        self._op_task = asyncio.create_task(
            self._supervise(self.operations[name], op_ctx), name=f"operation-{name}"
        )

    async def _supervise(self, operation: Operation, op_ctx: OperationContext) -> None:
        """Run one operation under processing_timeout (paused time excluded); post its outcome."""
        budget = self.settings.processing_timeout
        task = asyncio.ensure_future(operation(op_ctx))
        started = time.monotonic()
        try:
            while not task.done():
                remaining = budget - (time.monotonic() - started - op_ctx.gate.paused_seconds())
                if remaining <= 0 and not op_ctx.gate.paused:
                    task.cancel()
                    await asyncio.gather(task, return_exceptions=True)
                    self._post_failure(
                        op_ctx.run_id,
                        "OPERATION_TIMEOUT",
                        f"operation exceeded processing_timeout ({budget:g} s)",
                        "operation",
                    )
                    return
                await asyncio.wait({task}, timeout=max(remaining, 0.05))
            result = task.result()
        except asyncio.CancelledError:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            raise
        except OperationError as exc:
            self._post_failure(op_ctx.run_id, exc.code, str(exc), "operation")
            return
        except DeviceError as exc:
            self._post_failure(op_ctx.run_id, "DEVICE_FAULT", str(exc), exc.device)
            return
        except Exception as exc:
            log.exception("operation %s crashed", op_ctx.run_id)
            self._post_failure(
                op_ctx.run_id, "INTERNAL", f"{type(exc).__name__}: {exc}", "operation"
            )
            return
        self.submit(
            Event.OPERATION_COMPLETED,
            source="operation",
            data={"run_id": op_ctx.run_id, "result": result},
            bounded=False,
        )

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

    async def _bring_up_devices(self) -> None:
        timeouts = {
            "robot": self.settings.robot_communication_timeout,
            "glue": self.settings.glue_system_timeout,
            "camera": self.settings.vision_processing_timeout,
        }
        ready_event = {device: event for event, device in READINESS_EVENTS.items()}

        async def bring_up(name: str) -> None:
            try:
                await self.devices.connect(name, timeouts[name])
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                reason = "no answer" if isinstance(exc, TimeoutError) else str(exc)
                self._post_fault(
                    DeviceFault(
                        name,
                        "DEVICE_UNAVAILABLE",
                        f"{name} did not come up within {timeouts[name]:g} s: {reason}",
                    )
                )
                return
            self.submit(ready_event[name], source=name, bounded=False)

        await asyncio.gather(*(bring_up(name) for name in timeouts))

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

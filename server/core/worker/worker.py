"""The worker: the one consumer of the event queue and the only code that changes state.

It takes one envelope at a time, asks the pure engine for a decision, and runs
the decision's actions in their order (`server.core.machine.actions`), one handler per
action. After the exit actions it checks that no emergency stop came in
meanwhile; a decision overtaken by a stop is abandoned unless it leads to
ERROR itself. Then the sender's future gets the outcome, once the event and
what it caused are durable in the journal (`recorder.py`).

Operations and devices talk back only by posting events (OPERATION_COMPLETED,
OPERATION_FAILED, ERROR_OCCURRED), which keeps every change of state in this
one loop. A reset is decided when the devices have answered its live probe,
which runs without holding the loop (`reset_probe.py`).

Running operations is `runs.py`; start-up and homing `startup.py`; warnings
and the ERROR-timeout alert `alerts.py`.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace

from server.common.errors import EventQueueFull, TransitionNotAllowed, WorkerStopped
from server.common.event_id import current_event_id
from server.core.infra.bus import Bus
from server.core.infra.clock import SYSTEM_CLOCK, Clock
from server.core.machine.actions import EXIT_ACTIONS, Action
from server.core.machine.engine import REQUIRED_DEVICES, Decision, Facts, step
from server.core.machine.events import (
    AuditNote,
    FaultPayload,
    JogPayload,
    Outcome,
    Payload,
    RunCompletedPayload,
    payload_of,
)
from server.core.machine.preconditions import Preconditions
from server.core.machine.transitions import (
    COMMANDS,
    OPERATION_OF_STATE,
    READINESS_EVENTS,
    Event,
    State,
    event_label,
)
from server.core.operations.base import Operation
from server.core.operations.jog import JogRefused, jog_target, read_pose_within
from server.core.worker.alerts import Alerts
from server.core.worker.context import FaultRecord, MachineContext, ProcessingStats
from server.core.worker.devices import CellDevices
from server.core.worker.event_queue import Envelope, EventQueue, Priority
from server.core.worker.recorder import Recorder
from server.core.worker.reset_probe import RESET_OVERTAKEN, RESET_UNDER_WAY, ResetProbes
from server.core.worker.runs import PauseNotHeld, Runs
from server.core.worker.snapshot import SnapshotFile
from server.core.worker.startup import Activities
from server.core.worker.stop import EmergencyStops
from server.core.worker.view import CellView
from server.drivers.base import DeviceFault
from server.settings.model import Settings
from server.storage import CellStores
from server.storage.journal import Journal

log = logging.getLogger(__name__)

COMPLETION_EVENTS = frozenset({Event.OPERATION_COMPLETED, Event.OPERATION_FAILED})
OVERTAKEN = "overtaken by an emergency stop while it was being decided; nothing was changed"
# A person's commands, each answered only once on record: refused while the journal cannot
# write. The e-stop is not among them: it stops the cell whatever the disk says.
JOURNALED_COMMANDS = frozenset(COMMANDS.values()) - {Event.EMERGENCY_STOP}
Handler = Callable[[Decision, Envelope], Awaitable[None] | None]


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
        journal: Journal,
        snapshot_file: SnapshotFile | None = None,
        interruption: str | None = None,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.settings = settings
        self.devices = devices
        self.bus = bus
        self.interruption = interruption  # why the last run of the server ended mid-operation
        self.clock = clock
        self.ctx = MachineContext(history_size=settings.history_size)
        self.queue = EventQueue(settings.event_queue_size)
        self.stats = ProcessingStats(settings.performance_history_size)
        self.recorder = Recorder(journal, self._post_fault, self.ctx, snapshot_file, clock)
        self.alerts = Alerts(settings, self.ctx, bus, self.recorder, clock)
        self.runs = Runs(
            settings=settings,
            devices=devices,
            operations=operations,
            stores=stores,
            ctx=self.ctx,
            bus=bus,
            recorder=self.recorder,
            alerts=self.alerts,
            clock=clock,
            post_outcome=self._post_outcome,
        )
        self.activities = Activities(
            settings, devices, self._halt, self._post_ready, self._post_fault
        )
        self.preconditions = Preconditions(stores, settings)  # what a command needs first
        # Every e-stop: its halt at once, its event ahead of the queue, its answer (stop.py).
        self.stops = EmergencyStops(
            devices, self.runs.cut_leash, self.submit, settings.emergency_stop_timeout
        )
        self.view = CellView(self)  # what the API, the hub and metrics read
        self._ready: set[str] = set()
        self._ready_now: frozenset[str] = frozenset()  # _ready as the guards see it, kept
        self._boot = secrets.token_hex(3)
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._faults = 0  # faults recorded so far; a reset probed meanwhile is overtaken
        self._faults_posted = 0  # faults reported so far, decided or still queued (see jog)
        self.reset_probes = ResetProbes(
            devices, settings.reset_probe_timeout, lambda e: self.queue.put(e, bounded=False)
        )
        self._handlers: dict[Action, Handler] = {
            Action.HALT: lambda _d, e: self._halt(e),
            Action.RECORD_RUN_END: lambda d, e: self.runs.record_end(d.event, e.payload),
            Action.CANCEL_RUN: lambda _d, _e: self.runs.cancel(),
            Action.CANCEL_HOMING: lambda _d, _e: self.activities.cancel(),
            Action.HOLD: lambda _d, _e: self.runs.hold_now(),
            Action.RECORD_FAULT: self._record_fault,
            Action.CHANGE_STATE: self._change_state,
            Action.NOTE_READY: self._note_ready,
            Action.ENTER_IDLE: self._enter_idle,
            Action.START_HOMING: lambda _d, _e: self.activities.go_home(),
            Action.START_JOG: self._start_jog,
            Action.START_RUN: self._start_run,
            Action.OPEN_GATE: lambda _d, _e: self.runs.release(),
        }
        assert set(self._handlers) == set(Action), "every action needs its handler"

    # --- lifecycle ---------------------------------------------------------

    async def start(self) -> None:
        """Enter INITIALIZING, connect the devices, and begin draining the queue."""
        self._loop = asyncio.get_running_loop()
        self.devices.set_fault_listener(self.report_fault)
        self.ctx.since = self.clock.time()
        self._task = asyncio.create_task(self._run(), name="cell-worker")
        self.activities.bring_up(self.interruption)

    async def stop(self) -> None:
        """Stop draining; every waiting sender gets WorkerStopped, never a hang."""
        if self._task is not None:
            self._task.cancel()
        self.alerts.stop()
        probing = await self.reset_probes.stop()  # a reset waiting for its probe's answer
        await asyncio.gather(
            *(t for t in (self._task,) if t is not None),
            self.runs.stop(),
            self.activities.stop(),
            return_exceptions=True,
        )
        for envelope in self.queue.drain() + probing:
            if envelope.future is not None and not envelope.future.done():
                envelope.future.set_exception(WorkerStopped("the server is shutting down"))
        self.devices.set_fault_listener(None)

    @property
    def _estops(self) -> int:
        """E-stops begun so far (`EmergencyStops.requested`): a decision that saw fewer
        than there are now was overtaken by a stop (see _handle)."""
        return self.stops.requested

    # --- posting events ----------------------------------------------------

    def submit(
        self,
        event: Event,
        *,
        source: str,
        payload: Payload | None = None,
        priority: Priority = Priority.REQUEST,
        bounded: bool = True,
        audit: AuditNote | None = None,
    ) -> Envelope:
        """Queue an event (loop thread only). Raises EventQueueFull when `bounded` and full."""
        payload = payload_of(event, payload)
        loop = self._loop or asyncio.get_running_loop()
        if bounded and self.recorder.behind:
            raise EventQueueFull(self.queue.capacity)  # the disk is behind: refuse, never drop
        envelope = Envelope(
            event_id=f"{self._boot}-{next(self._ids):06d}",
            event=event,
            source=source,
            payload=payload,
            priority=priority,
            future=loop.create_future(),
            audit=audit,
        )
        self.queue.put(envelope, bounded=bounded)
        return envelope

    async def request(
        self,
        event: Event,
        *,
        source: str,
        payload: Payload | None = None,
        audit: AuditNote | None = None,
    ) -> Outcome:
        """Queue a request and wait for the worker's decision.

        Raises JournalUnavailable when the journal's last write failed and it still
        cannot write: nothing is decided that could not be put on record.
        """
        await self.recorder.ensure_writable()
        envelope = self.submit(event, source=source, payload=payload, audit=audit)
        assert envelope.future is not None
        return await envelope.future

    def report_fault(self, fault: DeviceFault) -> None:
        """Fault listener for the drivers; safe to call from any thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(self._post_fault, fault)

    def _post_fault(self, fault: DeviceFault) -> None:
        self._faults_posted += 1
        envelope = self.submit(
            Event.ERROR_OCCURRED,
            source=fault.device,
            payload=FaultPayload(fault.code, fault.message, fault.device),
            priority=Priority.FAULT,
            bounded=False,
        )
        what = (fault.device, fault.code, fault.message, envelope.event_id)
        log.error("device fault: %s %s: %s (event %s)", *what)

    def _post_ready(self, event: Event, device: str) -> None:
        self.submit(event, source=device, bounded=False)

    def _post_outcome(self, event: Event, payload: Payload) -> None:
        priority = Priority.REQUEST if event is Event.OPERATION_COMPLETED else Priority.FAULT
        self.submit(event, source="operation", payload=payload, priority=priority, bounded=False)

    def facts(self) -> Facts:
        """Guard facts from what is known without asking the devices (a reset probes them)."""
        devices = self.devices
        known: list[str] = []
        for name, device in (
            ("robot", devices.robot),
            ("glue", devices.glue),
            ("camera", devices.camera),
        ):
            health = device.health
            if not health.connected:
                known.append(f"{name}: not connected")
            elif health.active_faults:
                known.extend(health.active_faults)
        return Facts(ready_devices=self._ready_now, active_faults=tuple(known))

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
                message = f"internal error while handling {event_label(envelope.event)}: {exc}"
                outcome = self._outcome(envelope, False, message)
            finally:
                current_event_id.reset(token)
            if outcome is None:  # a reset gone to probe the devices: decided when it is back
                await asyncio.sleep(0)
                continue
            self.stats.record(time.perf_counter() - started, accepted=outcome.accepted)
            durable = self.recorder.commit(envelope, outcome)
            self.recorder.answer_when_durable(envelope, outcome, durable)
            if envelope.priority is Priority.EMERGENCY and durable is not None:
                await self._let_commit_through(durable)
            # Let the loop run between events, so a long queue of quick refusals
            # never starves the HTTP handlers (the e-stop route above all). After
            # every event: letting it run only every 0.1 ms makes the worker about
            # 1.2x faster and the stop behind a full queue about 2 ms slower at p99
            # (docs/benchmarks.md, "Engine and worker").
            await asyncio.sleep(0)

    async def _let_commit_through(self, durable: asyncio.Future[None]) -> None:
        """Wait for an e-stop's commit (at most emergency_stop_timeout) before the next event.

        Why: the journal's writer thread needs the interpreter lock between its
        SQLite calls, and a worker draining a long queue holds it for a whole
        switch interval each time: with 10 000 requests queued the stop's
        one-row commit would take tens to hundreds of ms that way. Waiting here leaves the loop
        idle, so the writer runs at once; the queue waits a few ms, and only
        after a stop. Bounded, so a stalled disk cannot hold the worker.
        """
        await asyncio.wait((durable,), timeout=self.settings.emergency_stop_timeout)

    async def _handle(self, envelope: Envelope) -> Outcome | None:
        """The event's outcome, or None for a reset that went to probe the devices first."""
        event, state = envelope.event, self.ctx.state
        if event in COMPLETION_EVENTS and not self._is_current_run(envelope):
            return self._refuse(envelope, f"{event.value} of a run that already ended; ignored")
        facts = self.facts()
        estops = self._estops
        probe = self.reset_probes.returned(envelope)
        problem = self.recorder.write_problem if event in JOURNALED_COMMANDS else None
        if problem is not None:  # queued before the journal failed: decide nothing now
            refusal = self._refuse(envelope, f"refused: the journal cannot write ({problem})")
            return replace(refusal, journal_problem=problem)
        if probe is not None:  # a reset back from its probe
            if (self._estops, self._faults) != probe.stops:
                return self._refuse(envelope, RESET_OVERTAKEN)
            facts = Facts(ready_devices=facts.ready_devices, active_faults=tuple(probe.found))
            estops = probe.stops[0]
        elif event is Event.RESET_REQUESTED and state is State.ERROR:
            if self.reset_probes.under_way:
                return self._refuse(envelope, RESET_UNDER_WAY)
            self.reset_probes.start(envelope, (self._estops, self._faults))
            return None
        try:
            decision = step(state, event, facts)
        except TransitionNotAllowed as refusal:
            return self._refuse(envelope, str(refusal))
        unmet = self.preconditions.check(event, envelope.payload)
        if unmet is not None:
            return self._refuse(envelope, unmet.message, unmet.field)
        overtakable = decision.target is not State.ERROR
        for action in decision.actions:
            if overtakable and action not in EXIT_ACTIONS:
                if self._estops != estops:
                    return self._refuse(envelope, OVERTAKEN)
                overtakable = False
            try:
                pending = self._handlers[action](decision, envelope)
                if pending is not None:
                    await pending
            except JogRefused as refused:  # found once the pose was read: nothing moved
                return self._refuse(envelope, refused.message, refused.field)
            except PauseNotHeld as exc:
                self._post_fault(DeviceFault(exc.component, "PAUSE_NOT_HELD", str(exc)))
                return self._refuse(envelope, f"pause not confirmed: {exc}; the cell stops")
        message = f"{event_label(event)} accepted: {state.value} → {decision.target.value}"
        started = envelope.event_id if Action.START_RUN in decision.actions else None
        return Outcome(True, envelope.event_id, event, self.ctx.state, message, run_id=started)

    def _outcome(
        self, envelope: Envelope, accepted: bool, message: str, field: str | None = None
    ) -> Outcome:
        return Outcome(accepted, envelope.event_id, envelope.event, self.ctx.state, message, field)

    def _refuse(self, envelope: Envelope, message: str, field: str | None = None) -> Outcome:
        who = (envelope.event.value, envelope.event_id, envelope.source, message)
        log.info("refused %s (%s) from %s: %s", *who)
        return self._outcome(envelope, False, message, field)

    def _is_current_run(self, envelope: Envelope) -> bool:
        run_id = getattr(envelope.payload, "run_id", None)
        return run_id is not None and self.runs.is_current(run_id)

    # --- action handlers ---------------------------------------------------

    async def _halt(self, envelope: Envelope | None = None) -> None:
        """Close the valve and stop the robot (valve first); an incomplete halt is alerted.

        The run's leash is cut first (a HALT always ends the run, if there is one):
        it commands nothing new, and an opening it had waiting for the dispenser's
        line is refused, so nothing it asked for goes out after this halt. One
        halt is enough, before the run's cancellation; once it has read the valve
        back closed, the run's own close as it ends is answered without another
        exchange (`Runs.halted`).

        An e-stop's HALT is the halt the stop made before it was queued (its leash
        cut as it arrived): the same two commands, already on their way. Sent
        again, they would only queue behind those on each device's line, and the
        stop's answer would wait a round trip more.
        """
        if envelope is not None and envelope.halt_made is not None:
            made, envelope.halt_made = envelope.halt_made, None
            report = await asyncio.shield(made)
        else:
            self.runs.cut_leash()
            report = await self.devices.safe_halt(self.settings.emergency_stop_timeout)
        self.runs.halted(report.valve_closed)
        self.alerts.halt_incomplete(report.errors)

    def _record_fault(self, decision: Decision, envelope: Envelope) -> None:
        fault = FaultRecord.of(
            envelope.payload, envelope.source, envelope.event_id, self.clock.time()
        )
        self.ctx.record_error(fault)
        self._faults += 1
        self.recorder.fault(fault, decision.target.value)
        running = self.ctx.operation
        context = running.fault_context() if running else {"operation": None}
        where = (fault.code, fault.component, self.ctx.state.value, envelope.event_id)
        log.error(
            "fault %s from %s in %s state (%s)",
            *where,
            extra={"error": fault.message, "context": context},
        )
        self.bus.publish("error", {**fault.as_dict(), "state": decision.target.value})

    def _change_state(self, decision: Decision, envelope: Envelope) -> None:
        now = self.clock.time()
        record = self.ctx.enter(decision.target, decision.event.value, envelope.event_id, now)
        what = (
            record.old_state,
            record.new_state,
            record.event,
            envelope.event_id,
            envelope.source,
        )
        log.info("%s → %s on %s (%s, from %s)", *what)
        self.recorder.transition(record)
        snapshot = self.view.snapshot()
        self.recorder.save_snapshot(snapshot, self.ctx.operation)
        self.bus.publish(
            "state_changed", {**record.as_dict(), "source": envelope.source, "snapshot": snapshot}
        )
        self.alerts.watch_state(decision.target)

    def _note_ready(self, decision: Decision, envelope: Envelope) -> None:
        self._ready.add(READINESS_EVENTS[decision.event])
        self._ready_now = frozenset(self._ready)
        if self._ready >= REQUIRED_DEVICES and self.ctx.state is State.INITIALIZING:
            self.submit(Event.SYSTEM_READY, source="system", bounded=False)

    def _enter_idle(self, decision: Decision, envelope: Envelope) -> None:
        ctx = self.ctx
        if isinstance(envelope.payload, RunCompletedPayload):
            ctx.operation_result = envelope.payload.result.as_dict()
        ctx.operation_data = {}
        if decision.event is Event.RESET_REQUESTED:
            ctx.clear_error()

    async def _start_jog(self, decision: Decision, envelope: Envelope) -> None:
        """Read the pose, check the step's target against the workspace, then move.

        The pose is read here, in the worker, because the worker alone starts
        moves outside operations: read while no move is under way, it is where
        the step starts. The read is bounded by emergency_stop_timeout, so the
        worker is never held long; an e-stop or a fault while it was read
        refuses the jog before anything moves.
        """
        payload = envelope.payload
        assert isinstance(payload, JogPayload)
        if self.activities.moving:
            raise JogRefused("the robot is still moving (home or a jog): jog once it stands")
        estops, faults = self._estops, self._faults_posted
        limit = self.settings.emergency_stop_timeout
        try:
            pose = await read_pose_within(self.devices.robot, limit)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            reason = f"no answer within {limit:g} s" if isinstance(exc, TimeoutError) else exc
            message = f"the robot's position could not be read ({reason}); nothing moved"
            raise JogRefused(message) from None
        target = jog_target(pose, payload.axis, payload.distance_mm, self.settings)
        if (self._estops, self._faults_posted) != (estops, faults) or self.facts().active_faults:
            raise JogRefused("a stop or a fault came in while the jog was decided; nothing moved")
        self.activities.jog(target)

    def _start_run(self, decision: Decision, envelope: Envelope) -> None:
        name = OPERATION_OF_STATE[decision.target]
        self.runs.start(name, envelope.event_id, envelope.payload.as_dict())

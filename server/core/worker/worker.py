"""The worker: the one consumer of the event queue and the only code that changes state.

It takes one envelope at a time, gathers the facts (`facts.py`), asks the pure
decision (`server.core.machine.decide`) and executes what it is given: a
refusal, a reset's probe of the devices, or the decision's actions in their
order (`server.core.machine.actions`), one handler per action. At the
decision's checkpoint, after the exit actions, it asks the decision whether
an emergency stop came in meanwhile and abandons it if so. Then the sender's
future gets the outcome, once the event and what it caused are durable in
the journal (`recorder.py`).

Operations and devices talk back only by posting events (OPERATION_COMPLETED,
OPERATION_FAILED, ERROR_OCCURRED), which keeps every change of state in this
one loop. A reset is decided when the devices have answered its live probe,
which runs without holding the loop (`reset_probe.py`).

Running operations is `runs.py`; start-up and homing `startup.py`; a jog's
start `jogging.py`; faults, state changes and readiness `state_changes.py`;
warnings and the ERROR-timeout alert `alerts.py`; posting events `posting.py`;
the e-stop's halt, event and answer `stop.py`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable

from server.common.errors import WorkerStopped
from server.common.event_id import current_event_id
from server.core.infra.bus import Bus
from server.core.infra.clock import SYSTEM_CLOCK, Clock
from server.core.machine import decide
from server.core.machine.actions import Action
from server.core.machine.decisions import DecisionListeners, DecisionNote
from server.core.machine.engine import Decision, Facts
from server.core.machine.events import JogPayload, Outcome, Payload
from server.core.machine.transitions import OPERATION_OF_STATE, Event, State, event_label
from server.core.operations.base import Operation
from server.core.operations.jog import JogRefused
from server.core.worker import facts as gather
from server.core.worker.alerts import Alerts
from server.core.worker.care import CareMeter
from server.core.worker.context import MachineContext, ProcessingStats
from server.core.worker.devices import CellDevices
from server.core.worker.event_queue import Envelope, EventIds, EventQueue, Priority
from server.core.worker.facts import OrderSource, known_device_faults
from server.core.worker.jogging import start_jog
from server.core.worker.posting import EventPoster
from server.core.worker.purging import start_purge
from server.core.worker.recorder import Recorder
from server.core.worker.reset_probe import ResetProbes
from server.core.worker.runs import PauseNotHeld, Runs
from server.core.worker.snapshot import SnapshotFile
from server.core.worker.startup import Activities
from server.core.worker.state_changes import StateChanges
from server.core.worker.stop import EmergencyStops
from server.core.worker.view import CellView
from server.drivers.base import DeviceFault
from server.settings.model import Settings
from server.storage import CellStores
from server.storage.journal import Journal

log = logging.getLogger(__name__)

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
        ids = EventIds()  # every event's id, whoever queues it
        self.stats = ProcessingStats(settings.performance_history_size)
        self.recorder = Recorder(
            journal, lambda f: self.poster.post_fault(f), self.ctx, snapshot_file, clock
        )
        self.poster = poster = EventPoster(self.queue, ids, self.recorder)
        self.submit = poster.submit  # every sender's way into the queue
        self.request = poster.request  # a command, answered once decided and on record
        self.report_fault = poster.report_fault  # the drivers' fault listener, any thread
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
            post_outcome=poster.post_outcome,
        )
        # Wear counters, the maintenance schedule, pot life and glue level (care.py).
        self.care = CareMeter(lambda: settings, devices, journal, self.alerts, clock)
        self.runs.listeners.append(self.care.run_ended)
        self.activities = Activities(
            settings, devices, self._halt, poster.post_ready, poster.post_fault
        )
        # Every e-stop: its halt at once, its event ahead of the queue, its answer (stop.py).
        self.stops = EmergencyStops(
            devices, self.runs.cut_leash, self.queue, ids, settings.emergency_stop_timeout
        )
        self.stores = stores
        self.orders: OrderSource | None = None  # the order book, once the cell has one
        self.view = CellView(self)  # what the API, the hub and metrics read
        self.changes = StateChanges(
            self.ctx,
            self.recorder,
            bus,
            self.alerts,
            clock,
            self.view.snapshot,
            lambda: poster.post_ready(Event.SYSTEM_READY, "system"),
        )
        self._task: asyncio.Task[None] | None = None
        self._guard_facts = Facts()  # the last facts() (see there)
        self._counted = decide.NO_STOPS  # the last stops decision_facts counted, kept alike
        # Told of every verdict before its actions run (decisions.py says who needs it).
        self.decisions = DecisionListeners()
        self.reset_probes = ResetProbes(
            devices, settings.reset_probe_timeout, lambda e: self.queue.put(e, bounded=False)
        )
        self._handlers: dict[Action, Handler] = {
            Action.HALT: lambda _d, e: self._halt(e),
            Action.RECORD_RUN_END: lambda d, e: self.runs.record_end(d.event, e.payload),
            Action.CANCEL_RUN: self._cancel_run,
            Action.CANCEL_HOMING: lambda _d, _e: self.activities.cancel(),
            Action.HOLD: lambda _d, _e: self.runs.hold_now(),
            Action.RECORD_FAULT: self.changes.record_fault,
            Action.CHANGE_STATE: self.changes.change_state,
            Action.NOTE_READY: self.changes.note_ready,
            Action.ENTER_IDLE: self.changes.enter_idle,
            Action.START_HOMING: lambda _d, _e: self.activities.go_home(),
            Action.START_JOG: self._start_jog,
            Action.START_PURGE: self._start_purge,
            Action.START_RUN: self._start_run,
            Action.OPEN_GATE: lambda _d, _e: self.runs.release(),
        }
        assert set(self._handlers) == set(Action), "every action needs its handler"

    # --- lifecycle ---------------------------------------------------------

    async def start(self) -> None:
        """Enter INITIALIZING, connect the devices, and begin draining the queue."""
        self.poster.loop = asyncio.get_running_loop()
        self.devices.set_fault_listener(self.report_fault)
        self.ctx.since = self.clock.time()
        self._task = asyncio.create_task(self._run(), name="cell-worker")
        self.activities.bring_up(self.interruption)
        self.care.load(self.recorder.journal.path)
        self.care.start()

    async def stop(self) -> None:
        """Stop draining; every waiting sender gets WorkerStopped, never a hang."""
        if self._task is not None:
            self._task.cancel()
        self.alerts.stop()
        self.care.stop()
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

    # --- facts -------------------------------------------------------------

    def facts(self) -> Facts:
        """Guard facts from what is known without asking the devices (a reset probes them);
        the last ones again while nothing in them changed (asked for every event decided)."""
        ready, known = self.changes.ready_now, known_device_faults(self.devices)
        last = self._guard_facts
        if last.ready_devices is not ready or last.active_faults != known:
            last = self._guard_facts = Facts(ready, known)
        return last

    def decision_facts(
        self, event: Event, payload: Payload, probed: decide.Probed | None = None
    ) -> decide.Facts:
        """Everything the decision on `event` reads (`server.core.machine.decide`)."""
        running, orders, stops = self.ctx.operation, self.orders, self._counted
        requested, faults = self.stops.requested, self.changes.faults
        if stops.estops != requested or stops.faults != faults:
            stops = self._counted = decide.Stops(requested, faults)
        order = gather.active_order(orders) if orders is not None else None
        facts = decide.Facts(
            guards=self.facts(),
            journal_problem=self.recorder.write_problem,
            current_run=running.run_id if running is not None else None,
            stops=stops,
            probing=self.reset_probes.under_way,
            probed=probed,
            active_order=order,
        )
        if event in gather.LIBRARY_EVENTS:  # the library and pot life: read for these only
            facts.library = gather.library_for(event, payload, self.ctx.state, order, self.stores)
            if event is Event.START_REQUESTED:
                facts.glue_line_problem = self.care.start_problem()
        return facts

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
        """Decide the event, then execute the verdict; None for a reset gone to probe."""
        event, state = envelope.event, self.ctx.state
        probe = self.reset_probes.returned(envelope)  # a reset back from its probe
        probed = probe.facts() if probe is not None else None
        facts = self.decision_facts(event, envelope.payload, probed)
        facts.asked_at_estops = envelope.asked_at_estops
        verdict = decide.decide(state, event, envelope.payload, facts, self.settings)
        if self.decisions.listeners:
            self._tell(state, event, verdict)
        if isinstance(verdict, decide.Refusal):
            if verdict.payload is not None:
                envelope.payload = verdict.payload  # recorded as decided
            return self._refuse(envelope, verdict.message, verdict.field, verdict.journal_problem)
        if isinstance(verdict, decide.ProbeDevices):
            self.reset_probes.start(envelope, verdict.began)
            return None
        envelope.payload = verdict.payload
        decision = verdict.decision
        for index, action in enumerate(decision.actions):
            if index == verdict.checkpoint:
                overtaken = verdict.overtaken(self.stops.requested)
                if overtaken is not None:
                    return self._refuse(envelope, overtaken.message)
            try:
                pending = self._handlers[action](decision, envelope)
                if pending is not None:
                    await pending
            except JogRefused as refused:  # found once the pose was read: nothing moved
                return self._refuse(envelope, refused.message, refused.field)
            except PauseNotHeld as exc:
                self.poster.post_fault(DeviceFault(exc.component, "PAUSE_NOT_HELD", str(exc)))
                return self._refuse(envelope, f"pause not confirmed: {exc}; the cell stops")
        message = decide.accepted_message(state, event, decision.target)
        started = envelope.event_id if Action.START_RUN in decision.actions else None
        return Outcome(True, envelope.event_id, event, self.ctx.state, message, run_id=started)

    def _tell(self, state: State, event: Event, verdict: decide.Verdict) -> None:
        """The verdict to the decision listeners, before any of its actions."""
        now = self.clock.time()
        if isinstance(verdict, decide.Refusal):
            self.decisions.tell(DecisionNote(state, event, "refused", None, now))
        elif isinstance(verdict, decide.ProbeDevices):
            self.decisions.tell(DecisionNote(state, event, "probing", None, now))
        else:
            target = verdict.decision.target
            self.decisions.tell(DecisionNote(state, event, "accepted", target, now))

    def _outcome(
        self, envelope: Envelope, accepted: bool, message: str, field: str | None = None
    ) -> Outcome:
        return Outcome(accepted, envelope.event_id, envelope.event, self.ctx.state, message, field)

    def _refuse(
        self,
        envelope: Envelope,
        message: str,
        field: str | None = None,
        journal_problem: str | None = None,
    ) -> Outcome:
        who = (envelope.event.value, envelope.event_id, envelope.source, message)
        log.info("refused %s (%s) from %s: %s", *who)
        what = (envelope.event_id, envelope.event, self.ctx.state, message, field, journal_problem)
        return Outcome(False, *what)

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

    async def _cancel_run(self, decision: Decision, envelope: Envelope) -> None:
        """Cancel the running operation, noting it on the envelope for the fault's record."""
        envelope.interrupted = self.ctx.operation
        await self.runs.cancel()

    async def _start_jog(self, decision: Decision, envelope: Envelope) -> None:
        payload = envelope.payload
        assert isinstance(payload, JogPayload)
        await start_jog(
            payload,
            robot=self.devices.robot,
            activities=self.activities,
            settings=self.settings,
            stops=lambda: (self.stops.requested, self.poster.faults_posted),
            known_faults=lambda: known_device_faults(self.devices),
        )

    def _start_purge(self, decision: Decision, envelope: Envelope) -> None:
        devices = self.devices
        start_purge(
            robot=devices.robot,
            glue=devices.glue,
            activities=self.activities,
            settings=self.settings,
            care=self.care,
            stops=lambda: (self.stops.requested, self.poster.faults_posted),
            post_fault=self.poster.post_fault,
        )

    def _start_run(self, decision: Decision, envelope: Envelope) -> None:
        name = OPERATION_OF_STATE[decision.target]
        self.runs.start(name, envelope.event_id, envelope.payload.as_dict())

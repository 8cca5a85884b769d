"""The worker's handlers of the actions that change what the cell is, not what it moves.

RECORD_FAULT, CHANGE_STATE, NOTE_READY and ENTER_IDLE: the machine's context,
the journal's records, the bus and the alerts, kept in step. The worker calls
them in the order of the decision's actions (`machine/actions.py`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from server.core.infra.bus import Bus
from server.core.infra.clock import Clock
from server.core.machine.engine import REQUIRED_DEVICES, Decision
from server.core.machine.events import RunCompletedPayload
from server.core.machine.transitions import READINESS_EVENTS, Event, State
from server.core.worker.alerts import Alerts
from server.core.worker.context import FaultRecord, MachineContext
from server.core.worker.event_queue import Envelope
from server.core.worker.recorder import Recorder

log = logging.getLogger(__name__)


class StateChanges:
    """Records faults, enters states, notes ready devices; counts the faults recorded."""

    def __init__(
        self,
        ctx: MachineContext,
        recorder: Recorder,
        bus: Bus,
        alerts: Alerts,
        clock: Clock,
        snapshot: Callable[[], dict[str, Any]],
        post_system_ready: Callable[[], None],
    ) -> None:
        self.ctx = ctx
        self.recorder = recorder
        self.bus = bus
        self.alerts = alerts
        self.clock = clock
        self._snapshot = snapshot
        self._post_system_ready = post_system_ready
        self._ready: set[str] = set()
        self.ready_now: frozenset[str] = frozenset()  # the devices ready, as the guards see it
        self.faults = 0  # faults recorded so far; a reset probed meanwhile is overtaken

    def record_fault(self, decision: Decision, envelope: Envelope) -> None:
        """The fault in the context (the first since a reset is the stop reason), the
        journal, the log and on the bus."""
        fault = FaultRecord.of(
            envelope.payload,
            envelope.source,
            envelope.event_id,
            self.clock.time(),
            # the run this transition cancelled, or one still running (a fault in PAUSED)
            envelope.interrupted or self.ctx.operation,
        )
        self.ctx.record_error(fault)
        self.faults += 1
        self.recorder.fault(fault, decision.target.value)
        where = (fault.code, fault.component, self.ctx.state.value, envelope.event_id)
        log.error(
            "fault %s from %s in %s state (%s)",
            *where,
            extra={"error": fault.message, "context": fault.context, "trace": fault.trace},
        )
        self.bus.publish(
            "error",
            {**fault.as_dict(), "context": fault.context, "state": decision.target.value},
        )

    def change_state(self, decision: Decision, envelope: Envelope) -> None:
        """Enter the decision's target: history, journal, snapshot, bus, the ERROR alert."""
        now = self.clock.time()
        record = self.ctx.enter(decision.target, str(decision.event), envelope.event_id, now)
        what = (
            record.old_state,
            record.new_state,
            record.event,
            envelope.event_id,
            envelope.source,
        )
        log.info("%s → %s on %s (%s, from %s)", *what)
        self.recorder.transition(record)
        snapshot = self._snapshot()
        self.recorder.save_snapshot(snapshot, self.ctx.operation)
        self.bus.publish(
            "state_changed", {**record.as_dict(), "source": envelope.source, "snapshot": snapshot}
        )
        self.alerts.watch_state(decision.target)

    def note_ready(self, decision: Decision, envelope: Envelope) -> None:
        """A device reported ready; SYSTEM_READY follows once all have, while INITIALIZING."""
        self._ready.add(READINESS_EVENTS[decision.event])
        self.ready_now = frozenset(self._ready)
        if self._ready >= REQUIRED_DEVICES and self.ctx.state is State.INITIALIZING:
            self._post_system_ready()

    def enter_idle(self, decision: Decision, envelope: Envelope) -> None:
        """Keep the run's result, clear its data, and on a reset the stop reason."""
        ctx = self.ctx
        if isinstance(envelope.payload, RunCompletedPayload):
            ctx.operation_result = envelope.payload.result.as_dict()
        ctx.operation_data = {}
        if decision.event is Event.RESET_REQUESTED:
            ctx.clear_error()

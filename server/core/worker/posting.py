"""Putting events on the worker's queue: commands, device faults, readiness, run outcomes.

Every sender but the e-stop goes through here, so every envelope gets its event
id (`EventIds`) and its future, and a full request lane or a journal behind its
writes refuses loudly instead of dropping anything. The e-stop queues its own
event (server/core/worker/stop.py: `Stop.post`): it is never refused, and its
halt is already made when it is queued.
"""

from __future__ import annotations

import asyncio
import logging

from server.common.errors import EventQueueFull
from server.core.machine.events import AuditNote, FaultPayload, Outcome, Payload, payload_of
from server.core.machine.transitions import Event
from server.core.worker.event_queue import Envelope, EventIds, EventQueue, Priority
from server.core.worker.recorder import Recorder
from server.drivers.base import DeviceFault

log = logging.getLogger(__name__)


class EventPoster:
    """Queues the worker's events; counts the faults reported (decided or still queued)."""

    def __init__(self, queue: EventQueue, ids: EventIds, recorder: Recorder) -> None:
        self.queue = queue
        self.ids = ids
        self.recorder = recorder
        self.loop: asyncio.AbstractEventLoop | None = None  # the worker's, once started
        self.faults_posted = 0

    def submit(
        self,
        event: Event,
        *,
        source: str,
        payload: Payload | None = None,
        priority: Priority = Priority.REQUEST,
        bounded: bool = True,
        audit: AuditNote | None = None,
        asked_at_estops: int | None = None,
    ) -> Envelope:
        """Queue an event (loop thread only). Raises EventQueueFull when `bounded` and full."""
        payload = payload_of(event, payload)
        loop = self.loop or asyncio.get_running_loop()
        if bounded and self.recorder.behind:
            raise EventQueueFull(self.queue.capacity)  # the disk is behind: refuse, never drop
        envelope = Envelope(
            event_id=self.ids.next(),
            event=event,
            source=source,
            payload=payload,
            priority=priority,
            future=loop.create_future(),
            audit=audit,
            asked_at_estops=asked_at_estops,
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
        asked_at_estops: int | None = None,
    ) -> Outcome:
        """Queue a request and wait for the worker's decision; `asked_at_estops`, the
        e-stops counted when it reached its door (refused if one was made since).

        Raises JournalUnavailable when the journal's last write failed and it still
        cannot write: nothing is decided that could not be put on record.
        """
        await self.recorder.ensure_writable()
        envelope = self.submit(
            event, source=source, payload=payload, audit=audit, asked_at_estops=asked_at_estops
        )
        assert envelope.future is not None
        return await envelope.future

    def report_fault(self, fault: DeviceFault) -> None:
        """Fault listener for the drivers; safe to call from any thread."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(self.post_fault, fault)

    def post_fault(self, fault: DeviceFault) -> None:
        """Queue ERROR_OCCURRED for `fault` in the fault lane (never refused)."""
        self.faults_posted += 1
        envelope = self.submit(
            Event.ERROR_OCCURRED,
            source=fault.device,
            payload=FaultPayload(fault.code, fault.message, fault.device),
            priority=Priority.FAULT,
            bounded=False,
        )
        what = (fault.device, fault.code, fault.message, envelope.event_id)
        log.error("device fault: %s %s: %s (event %s)", *what)

    def post_ready(self, event: Event, device: str) -> None:
        """Queue a device's readiness event (or SYSTEM_READY, from "system")."""
        self.submit(event, source=device, bounded=False)

    def post_outcome(self, event: Event, payload: Payload) -> None:
        """Queue a run's OPERATION_COMPLETED (request lane) or OPERATION_FAILED (fault lane)."""
        priority = Priority.REQUEST if event is Event.OPERATION_COMPLETED else Priority.FAULT
        self.submit(event, source="operation", payload=payload, priority=priority, bounded=False)

"""The e-stop, owned in one place: its halt, its event and its answer.

A stop does not wait in the queue (DESIGN.md, principle 4). `EmergencyStops.begin`
makes its first moves at once, in this order: the count of stops goes up (so
anything the worker is deciding from then on cannot undo the stop: the
overtaken rule in `Worker._handle`), the running operation's leash is cut (it
commands no move and no glue from then on), and the one halt there is
(`CellDevices.safe_halt`) starts as a task whose first step has run
(`eager.start_task`): both devices' frames are written before `begin` returns,
with no garbage collection and no background thread in between
(`collection_deferred`, `background_held`; server/common/runtime.py says why).

The `Stop` it returns carries that halt to its end: `finish` puts the
EMERGENCY_STOP in the queue's top lane itself (never bounded, never refused, so
no poster stands between the stop and the worker; the worker's HALT action
takes the halt already made instead of commanding the devices again) and
answers once the worker has decided it and the halt has reported. Every door
makes its stop here: HTTP in its stop lane (server/api/stop_lane.py: begun as
the request passes the access gate, finished there with the body's reason);
MQTT, OPC UA and the façade through `EmergencyStops.stop`, both at once.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from server.common.runtime import background_held, collection_deferred
from server.core.infra.eager import start_task
from server.core.machine.events import AuditNote, Outcome, StopPayload
from server.core.machine.transitions import Event
from server.core.worker.devices import CellDevices, HaltReport
from server.core.worker.event_queue import Envelope, EventIds, EventQueue, Priority

log = logging.getLogger(__name__)


def halt_at_once(devices: CellDevices, timeout: float) -> asyncio.Future[HaltReport]:
    """The safe halt as a task whose first step has run: both frames written on return.

    Not a coroutine, so no turn of a possibly busy loop comes first, nor a garbage
    collection (`collection_deferred`) or a journal commit (`background_held`)
    between the two frames (unless a device's line is busy with an exchange
    already under way: then its command waits for that reply).
    """
    with collection_deferred(), background_held():
        return start_task(devices.safe_halt(timeout))


class Stop:
    """One e-stop from its halt to its answer (made by `EmergencyStops.begin`).

    Posted once: whoever finishes it first gives the event its source, reason
    and audit note; `post` after that returns the same envelope.
    """

    def __init__(self, halt: asyncio.Future[HaltReport], queue: EventQueue, ids: EventIds) -> None:
        self.halt = halt
        self._queue = queue
        self._ids = ids
        self.envelope: Envelope | None = None

    @property
    def posted(self) -> bool:
        return self.envelope is not None

    def post(
        self,
        *,
        source: str,
        payload: StopPayload | None = None,
        audit: AuditNote | None = None,
    ) -> Envelope:
        """Queue the EMERGENCY_STOP of this halt in the top lane, ahead of everything
        waiting (not bounded: never refused, not even with the journal behind)."""
        if self.envelope is None:
            self.envelope = Envelope(
                event_id=self._ids.next(),
                event=Event.EMERGENCY_STOP,
                source=source,
                payload=payload or StopPayload(),
                priority=Priority.EMERGENCY,
                future=asyncio.get_running_loop().create_future(),
                audit=audit,
                halt_made=self.halt,
            )
            self._queue.put(self.envelope, bounded=False)
        return self.envelope

    async def finish(
        self,
        *,
        source: str,
        payload: StopPayload | None = None,
        audit: AuditNote | None = None,
    ) -> Outcome:
        """Post the stop's event and answer once it is decided and the halt has reported.

        The halt is shielded: a caller that goes away (a client that disconnects)
        cannot cancel the devices' halt. An incomplete halt is said in the answer.
        """
        envelope = self.post(source=source, payload=payload, audit=audit)
        assert envelope.future is not None
        report = await asyncio.shield(self.halt)
        outcome: Outcome = await envelope.future
        if report.errors:
            return outcome.with_note(f"; halt incomplete: {'; '.join(report.errors)}")
        return outcome


class EmergencyStops:
    """Makes every e-stop of one worker; counts them for the worker's overtaken rule."""

    def __init__(
        self,
        devices: CellDevices,
        cut_leash: Callable[[], None],
        queue: EventQueue,
        ids: EventIds,
        timeout: float,
    ) -> None:
        self._devices = devices
        self._cut_leash = cut_leash  # the running operation's (Runs.cut_leash)
        self._queue = queue  # the worker's: the stop's event goes in its top lane
        self._ids = ids  # the worker's event ids, shared with its poster
        self._timeout = timeout  # emergency_stop_timeout: each halt command's bound
        self.requested = 0  # e-stops begun so far
        # When the last stop's halt began, its frames written to the devices' sockets
        # straight after (Unix time, as a device's own clock notes their arrival): splits
        # a stop's time into the server's part and the devices' (bench.estop_doors).
        self.last_halted_at: float | None = None

    def begin(self) -> Stop:
        """The stop's first moves, at once (module docstring); its event must follow."""
        self.requested += 1
        self._cut_leash()
        self.last_halted_at = time.time()
        return Stop(halt_at_once(self._devices, self._timeout), self._queue, self._ids)

    async def stop(
        self,
        *,
        source: str,
        payload: StopPayload | None = None,
        audit: AuditNote | None = None,
    ) -> Outcome:
        """A whole e-stop: halt the devices now, then have the machine go to ERROR."""
        return await self.begin().finish(source=source, payload=payload, audit=audit)

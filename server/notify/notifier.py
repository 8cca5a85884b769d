"""The webhooks' one bus subscriber: turns the cell's records into notices for each webhook.

Why a bus subscriber (plus the run-ended hook, which the bus has no record of):
like the WebSocket hub, it is fed without the worker ever waiting for it. Its
subscription is bounded; should it ever fall behind and be closed as a slow
consumer, it subscribes again and counts what it missed (`missed` at GET
/webhooks), and the worker is not held up. Each notice is then handed to the
webhooks whose filter names its kind, each with its own bounded queue and
delivery task (`deliverer.py`).

Order: a completed run is heard from the worker (CellView.on_run_ended) before
the state change that follows it is published, while records published before
it may still sit in the subscription's buffer. So the run's notice is held
until every record published before it has been handled (by bus seq), and a
receiver sees a run's notices in the order they happened.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from server.core.infra.bus import Bus, BusMessage, Subscription, SubscriptionClosed
from server.core.worker.runs import RunEnded
from server.core.worker.view import CellView
from server.notify import notices
from server.notify.deliverer import Deliverer
from server.notify.notices import Notice
from server.security import destinations
from server.settings.notifications import WebhookSettings
from server.storage.journal import Journal

if TYPE_CHECKING:  # imported when a webhook starts: a cell with none never loads httpx
    import httpx

log = logging.getLogger(__name__)

SUBSCRIPTION_BUFFER = 1024  # bus records; each is handled in microseconds


class Notifier:
    """Feeds every configured webhook.

    Built by the composition root (`server/bootstrap/plant.py: webhooks_of`) with the
    cell's bus, before the cell starts: with a webhook configured it subscribes then,
    so it hears every record the worker publishes from its first (the start-up's own
    change into IDLE included), however long the rest of the cell's start takes.
    `start` once the cell has started (its view and journal exist), `stop` before the
    journal closes, so what the deliverers abandon is on record.
    """

    def __init__(self, settings: WebhookSettings, cell_id: str, bus: Bus) -> None:
        self.settings = settings
        self.cell_id = cell_id
        self._bus = bus
        self._view: CellView | None = None
        self._client: httpx.AsyncClient | None = None
        self.deliverers: list[Deliverer] = []
        self._held: deque[tuple[int, Notice]] = deque()  # run notices waiting for a bus seq
        self._handled_seq = 0
        # No webhook: no subscription, no task, no cost.
        self._subscription: Subscription | None = self._subscribe() if settings.webhooks else None
        self._task: asyncio.Task[None] | None = None
        self.missed = 0  # bus records lost to a slow-consumer close

    def start(self, view: CellView, journal: Journal) -> None:
        """Start each webhook's delivery and the feeding; the cell is started already."""
        if self._subscription is None:
            return
        import httpx

        settings = self.settings
        self._view = view
        self._client = httpx.AsyncClient(
            timeout=httpx.Timeout(settings.webhook_timeout),
            follow_redirects=False,  # the signed notice goes where it was configured to
            trust_env=False,  # straight to the receiver: no proxy from the environment
            # every connection's address checked against the destination policy
            transport=destinations.guarded_transport(
                destinations.parse_networks(settings.webhook_allowed_networks)
            ),
        )
        self.deliverers = [
            Deliverer(t, settings, self.cell_id, self._client, journal) for t in settings.webhooks
        ]
        for deliverer in self.deliverers:
            deliverer.start()
        self._task = asyncio.create_task(self._consume(), name="webhook-notifier")
        if any({"run_completed", "part"} & set(d.target.events) for d in self.deliverers):
            view.on_run_ended(self._run_ended)
        names = ", ".join(f"{d.name} ({d.target.shown_url})" for d in self.deliverers)
        log.info("webhooks: %s", names)

    async def stop(self) -> None:
        """Stop feeding; each webhook journals what it abandons (the journal is still open)."""
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None
        if self._subscription is not None:
            self._subscription.close()
        self._release(self._bus.last_seq)
        for deliverer in self.deliverers:
            await deliverer.stop()
        if self._client is not None:
            await self._client.aclose()
            self._client = None

    def status(self) -> dict[str, Any]:
        """GET /webhooks: each webhook redacted, with its queue and counters."""
        s = self.settings
        return {
            "webhooks": [d.status() for d in self.deliverers],
            "missed": self.missed,
            "cell_id": self.cell_id,
            "timeout_s": s.webhook_timeout,
            "max_attempts": s.webhook_max_attempts,
            "retry_delay_s": s.webhook_retry_delay,
            "retry_max_delay_s": s.webhook_retry_max_delay,
        }

    # --- feeding -----------------------------------------------------------

    def _subscribe(self) -> Subscription:
        return self._bus.subscribe(SUBSCRIPTION_BUFFER, types=notices.BUS_TYPES)

    async def _consume(self) -> None:
        assert self._subscription is not None
        while True:
            try:
                message = await self._subscription.get()
            except SubscriptionClosed:
                # Fell behind: start again from now, and say how much was missed.
                self.missed += max(0, self._bus.last_seq - self._handled_seq)
                self._subscription = self._subscribe()
                self._release(self._bus.last_seq)
                self._handled_seq = self._bus.last_seq
                continue
            self._handle(message)

    def _handle(self, message: BusMessage) -> None:
        self._release(message.seq - 1)  # a run that ended before this record
        try:
            notice = notices.from_bus(message, self._state)
        except (KeyError, TypeError, ValueError) as exc:  # a record of an unexpected shape
            log.error(
                "webhooks: cannot make a notice of %s #%d: %s", message.type, message.seq, exc
            )
            notice = None
        if notice is not None:
            self._fan_out(notice)
        self._handled_seq = message.seq
        self._release(message.seq)

    def _state(self) -> str:
        """The cell's state now, for a notice's head (fed only once started)."""
        assert self._view is not None
        return self._view.state.value

    def _run_ended(self, ended: RunEnded) -> None:
        """In the worker: only appends (see the module docstring for the order)."""
        at = time.time()
        told = [n for n in (notices.from_run(ended, at), notices.from_part(ended, at)) if n]
        if not told:
            return
        self._held.extend((self._bus.last_seq, notice) for notice in told)
        if self._handled_seq >= self._bus.last_seq:
            self._release(self._handled_seq)

    def _release(self, through_seq: int) -> None:
        while self._held and self._held[0][0] <= through_seq:
            self._fan_out(self._held.popleft()[1])

    def _fan_out(self, notice: Notice) -> None:
        for deliverer in self.deliverers:
            if deliverer.wants(notice):
                deliverer.offer(notice)

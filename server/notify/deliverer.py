"""One webhook's bounded queue and the task that delivers it, attempt by attempt.

Why a task per webhook, in order: a receiver sees a cell's notices in the order
they happened (a retry holds up the notices behind it to the same webhook, not
to the others). Why bounded, dropping the oldest: a dead receiver must cost a
fixed amount of memory however long it is away, and what it missed while the
queue was full is counted and journaled (outcome `dropped`), so nothing is lost
without a trace. Nothing here is awaited by the worker: `offer` appends and
returns.

Every notice's outcome is one journal row once it is final (delivered,
refused, failed after the last attempt, dropped, or abandoned when the server
stopped), with each attempt's time, duration, status and error.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from server.notify import retry, signing
from server.notify.notices import Notice
from server.security.destinations import DestinationRefused
from server.settings.notifications import WebhookSettings
from server.settings.webhooks import WebhookTarget
from server.storage.journal import Journal, records

if TYPE_CHECKING:
    import httpx

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Pending:
    """A notice addressed to this webhook: its id is the same on every attempt."""

    notice: Notice
    delivery_id: str = field(default_factory=lambda: uuid.uuid4().hex)
    tries: list[dict[str, Any]] = field(default_factory=list)


@dataclass(slots=True)
class Counters:
    delivered: int = 0
    refused: int = 0
    failed: int = 0
    dropped: int = 0
    abandoned: int = 0
    last: dict[str, Any] | None = None  # the last final outcome


class Deliverer:
    """Delivers the notices of one webhook; `offer` never waits."""

    def __init__(
        self,
        target: WebhookTarget,
        settings: WebhookSettings,
        cell_id: str,
        client: httpx.AsyncClient,
        journal: Journal,
    ) -> None:
        assert target.name is not None  # named by the settings (targets.named)
        self.target = target
        self.name = target.name
        self.settings = settings
        self.cell_id = cell_id
        self._client = client
        self._journal = journal
        self._queue: deque[Pending] = deque()
        self._maxsize = settings.webhook_queue_size
        self._ready = asyncio.Event()
        self._current: Pending | None = None
        self._task: asyncio.Task[None] | None = None
        self.counters = Counters()

    def wants(self, notice: Notice) -> bool:
        return notice.kind in self.target.events

    def offer(self, notice: Notice) -> None:
        """Queue `notice`; when the queue is full the oldest waiting one is dropped."""
        if len(self._queue) >= self._maxsize:
            oldest = self._queue.popleft()
            self._settle(oldest, "dropped", "the webhook's queue was full (webhook_queue_size)")
        self._queue.append(Pending(notice))
        self._ready.set()

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name=f"webhook-{self.name}")

    async def stop(self) -> None:
        """End at once: what is in flight or queued is journaled as abandoned."""
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None
        waiting = ([self._current] if self._current is not None else []) + list(self._queue)
        self._current = None
        self._queue.clear()
        for pending in waiting:
            self._settle(pending, "abandoned", "the server stopped before it was delivered")

    def status(self) -> dict[str, Any]:
        """The webhook, redacted, with its queue and counters (GET /webhooks)."""
        c = self.counters
        return {
            **self.target.public(),
            "queued": len(self._queue),
            "queue_size": self._maxsize,
            "in_flight": _in_flight(self._current),
            "delivered": c.delivered,
            "refused": c.refused,
            "failed": c.failed,
            "dropped": c.dropped,
            "abandoned": c.abandoned,
            "last": c.last,
        }

    # --- delivery ----------------------------------------------------------

    async def _run(self) -> None:
        while True:
            while not self._queue:
                self._ready.clear()
                await self._ready.wait()
            self._current = self._queue.popleft()
            outcome, error = await self._deliver(self._current)
            self._settle(self._current, outcome, error)
            self._current = None

    async def _deliver(self, pending: Pending) -> tuple[str, str]:
        """Attempt until delivered, refused or out of attempts; (outcome, last error)."""
        settings = self.settings
        body = pending.notice.body(pending.delivery_id, self.cell_id)
        error = ""
        for attempt in range(1, settings.webhook_max_attempts + 1):
            try:
                status, error, retry_after = await self._attempt(pending, body)
            except DestinationRefused as refused:
                return "refused", str(refused)  # the policy: no retry changes it
            if status is not None:
                verdict = retry.verdict(status)
                if verdict is retry.Verdict.DELIVERED:
                    return "delivered", ""
                if verdict is retry.Verdict.REFUSED:
                    return "refused", error
            if attempt < settings.webhook_max_attempts:
                wait = retry.delay(
                    attempt,
                    settings.webhook_retry_delay,
                    settings.webhook_retry_max_delay,
                    retry_after,
                )
                await asyncio.sleep(wait)
        return "failed", error

    async def _attempt(self, pending: Pending, body: bytes) -> tuple[int | None, str, float | None]:
        """One POST: (status or None, error text, Retry-After seconds); its try noted."""
        timestamp = int(time.time())
        headers = signing.headers(
            self.target.secret_value, timestamp, body, pending.delivery_id, pending.notice.kind
        )
        started = time.time()
        import httpx  # loaded already: the notifier made the client

        status: int | None = None
        error = ""
        retry_after = None
        try:
            async with asyncio.timeout(self.settings.webhook_timeout):
                response = await self._client.post(self.target.url, content=body, headers=headers)
            status = response.status_code
            if not 200 <= status < 300:
                error = f"HTTP {status} {response.reason_phrase}".strip()
            retry_after = retry.retry_after_seconds(response.headers.get("Retry-After"))
        except TimeoutError:
            error = f"no answer within {self.settings.webhook_timeout:g} s (webhook_timeout)"
        except httpx.HTTPError as exc:
            error = self._redacted(f"{type(exc).__name__}: {exc}".rstrip(": "))
        except DestinationRefused as exc:
            self._note(pending, started, None, f"refused: {exc}")
            raise
        self._note(pending, started, status, error)
        return status, error, retry_after

    @staticmethod
    def _note(pending: Pending, started: float, status: int | None, error: str) -> None:
        """One attempt on the notice's record: when, how long, the answer, the error."""
        pending.tries.append(
            {
                "at": started,
                "seconds": round(time.time() - started, 4),
                "status": status,
                "error": error,
            }
        )

    def _redacted(self, text: str) -> str:
        """An error text without the URL's path or query (they may hold a token)."""
        return text.replace(self.target.url, self.target.shown_url)

    def _settle(self, pending: Pending, outcome: str, error: str) -> None:
        """The notice's outcome is final: counted, logged when it failed, journaled."""
        now = time.time()
        c = self.counters
        setattr(c, outcome, getattr(c, outcome) + 1)
        c.last = {
            "outcome": outcome,
            "at": now,
            "kind": pending.notice.kind,
            "delivery_id": pending.delivery_id,
            "attempts": len(pending.tries),
            "error": error,
        }
        if outcome != "delivered":
            log.warning(
                "webhook %s (%s): %s notice %s %s after %d attempt(s): %s",
                self.name,
                self.target.shown_url,
                pending.notice.kind,
                pending.delivery_id,
                outcome,
                len(pending.tries),
                error,
            )
        record = records.webhook_delivery(
            now,
            pending.delivery_id,
            self.name,
            pending.notice.kind,
            pending.notice.at,
            outcome,
            pending.tries,
            error,
        )
        with contextlib.suppress(Exception):  # a journal that fails reports it itself
            self._journal.append([record], durable=False)


def _in_flight(pending: Pending | None) -> dict[str, Any] | None:
    """The notice being attempted now: its id, kind, attempts so far and last error."""
    if pending is None:
        return None
    last = pending.tries[-1] if pending.tries else None
    return {
        "delivery_id": pending.delivery_id,
        "kind": pending.notice.kind,
        "attempts": len(pending.tries),
        "last_error": last["error"] if last else None,
    }

"""The one bus on which the worker publishes what happens in the cell.

Every message gets a sequence number that rises by one, so a subscriber can
tell whether it missed something. Publishing never waits: each subscriber has
a bounded buffer, and a subscriber that lets it fill up is closed with the
reason `slow consumer` instead of holding up the worker or anyone else. The
WebSocket hub and the metrics are subscribers; the journal is not (it must
never be dropped, so the worker hands it records directly).

Publish from the event loop's thread only (other threads use
`loop.call_soon_threadsafe`).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

SLOW_CONSUMER = "slow consumer"


@dataclass(frozen=True, slots=True)
class BusMessage:
    """One published record: `type` is e.g. state_changed, progress, error."""

    seq: int
    type: str
    time: float
    data: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The wire form: the payload's keys beside seq, type and time."""
        return {"type": self.type, "seq": self.seq, "time": self.time, **self.data}


class SubscriptionClosed(Exception):
    """The subscription ended; `reason` says why (e.g. slow consumer)."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class Subscription:
    """A bounded mailbox of bus messages for one consumer."""

    def __init__(self, bus: Bus, maxsize: int, types: Iterable[str] | None) -> None:
        self._bus = bus
        self._maxsize = maxsize
        self._buffer: deque[BusMessage] = deque()
        self._ready = asyncio.Event()
        self.types: frozenset[str] | None = frozenset(types) if types is not None else None
        self.closed_reason: str | None = None

    @property
    def pending(self) -> int:
        return len(self._buffer)

    def wants(self, message_type: str) -> bool:
        return self.types is None or message_type in self.types

    def set_types(self, types: Iterable[str] | None) -> None:
        """Change which message types this subscriber receives from now on."""
        self.types = frozenset(types) if types is not None else None

    def offer(self, message: BusMessage) -> None:
        """Queue a message, or close the subscription if its buffer is full."""
        if self.closed_reason is not None or not self.wants(message.type):
            return
        if len(self._buffer) >= self._maxsize:
            self.close(SLOW_CONSUMER)
            return
        self._buffer.append(message)
        self._ready.set()

    async def get(self) -> BusMessage:
        """The next message; raises SubscriptionClosed once closed (buffer discarded)."""
        while True:
            if self.closed_reason is not None:
                raise SubscriptionClosed(self.closed_reason)
            if self._buffer:
                return self._buffer.popleft()
            self._ready.clear()
            await self._ready.wait()

    def close(self, reason: str = "closed") -> None:
        """Stop receiving; a waiting `get` raises SubscriptionClosed."""
        if self.closed_reason is None:
            self.closed_reason = reason
            self._buffer.clear()
            self._bus.unsubscribe(self)
            self._ready.set()


class Bus:
    """Fan-out of cell records to bounded subscribers, in publish order."""

    def __init__(self) -> None:
        self._subscribers: list[Subscription] = []
        self._seq = itertools.count(1)
        self.last_seq = 0

    @property
    def subscriber_count(self) -> int:
        return len(self._subscribers)

    def subscribe(self, maxsize: int = 256, types: Iterable[str] | None = None) -> Subscription:
        """A new subscription receiving every later message (of `types`, if given)."""
        subscription = Subscription(self, maxsize, types)
        self._subscribers.append(subscription)
        return subscription

    def unsubscribe(self, subscription: Subscription) -> None:
        if subscription in self._subscribers:
            self._subscribers.remove(subscription)

    def publish(self, message_type: str, data: dict[str, Any]) -> BusMessage:
        """Number the record and hand it to every subscriber without waiting."""
        self.last_seq = next(self._seq)
        message = BusMessage(self.last_seq, message_type, time.time(), data)
        for subscription in tuple(self._subscribers):
            subscription.offer(message)
        return message

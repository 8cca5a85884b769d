"""The one bus on which the worker publishes what happens in the cell.

Every message gets a sequence number that rises by one, so a subscriber can
tell whether it missed something. Publishing never waits: each subscriber has
a bounded buffer, and a subscriber that lets it fill up is closed with the
reason `slow consumer` instead of holding up the worker or anyone else. The
WebSocket hub and the metrics are subscribers; the journal is not (it must
never be dropped, so the worker hands it records directly).

Waking subscribers is spread over turns of the event loop, WAKE_BATCH at a
time: with a thousand WebSocket clients, waking them all at once would put a
thousand sends in one turn (tens of milliseconds) ahead of anything that
arrives meanwhile, such as an e-stop request. In batches, the loop checks its
sockets between every WAKE_BATCH sends; the fan-out as a whole takes as long
as before.

The bus also keeps the last REPLAY_HISTORY messages, so that a WebSocket
client that lost its connection can be sent what it missed (`since`) instead of
only being told how much that was. The ring is kept here, at publish, rather
than by a subscriber: a subscriber's copy would lag the numbering by whatever
sits in its buffer, and could itself be dropped as a slow consumer, leaving a
hole between what it kept and what a new subscription receives. `boot` names
this bus's numbering: seq starts again at 1 with every new bus (every server
process), so a seq only means something together with its boot.

Samples (`publish_sample`, SAMPLE_TYPES: the live `device` readings) are not
records: a missed one is replaced a tenth of a second later. They take no seq
number and are not kept in the ring (at ten a second they would push the
records out of it within two minutes of running), and a subscription receives
them only when it names their type: an "everything" subscription (types None)
means every record, so no existing consumer's stream changes.

Publish from the event loop's thread only (other threads use
`loop.call_soon_threadsafe`).
"""

from __future__ import annotations

import asyncio
import itertools
import secrets
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

SLOW_CONSUMER = "slow consumer"
WAKE_BATCH = 16  # subscribers woken per turn of the loop
# Messages kept for replay. Sized for a client's longest reconnect: the Python
# client's backoff is capped at 5 s (+20 % jitter), and a run publishes a progress
# message per waypoint (tens a second at most), so a few hundred cover it; four
# times the default ws_client_buffer (256) also lets a client dropped as a slow
# consumer catch up. Bounded by count, not time, so memory stays flat (each
# message is a dict of a few hundred bytes to a few KiB: a few MiB at most).
REPLAY_HISTORY = 1024
SAMPLE_TYPES = frozenset({"device"})  # unnumbered, not replayed, sent only when asked for


@dataclass(frozen=True, slots=True)
class BusMessage:
    """One published record: `type` is e.g. state_changed, progress, error."""

    seq: int
    type: str
    time: float
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def numbered(self) -> bool:
        """False for a sample (seq 0): see the module docstring."""
        return self.seq > 0

    def as_dict(self) -> dict[str, Any]:
        """The wire form: the payload's keys beside seq, type and time (a sample has no seq)."""
        if not self.numbered:
            return {"type": self.type, "time": self.time, **self.data}
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
        if self.types is None:
            return message_type not in SAMPLE_TYPES
        return message_type in self.types

    def set_types(self, types: Iterable[str] | None) -> None:
        """Change which message types this subscriber receives from now on."""
        self.types = frozenset(types) if types is not None else None

    def offer(self, message: BusMessage) -> bool:
        """Queue a message (True), or close the subscription if its buffer is full.

        The consumer is not woken here: the bus wakes it (see `Bus.publish`).
        """
        if self.closed_reason is not None or not self.wants(message.type):
            return False
        if len(self._buffer) >= self._maxsize:
            self.close(SLOW_CONSUMER)
            return False
        self._buffer.append(message)
        return True

    def wake(self) -> None:
        if self._buffer:
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

    def __init__(self, history: int = REPLAY_HISTORY) -> None:
        self._subscribers: list[Subscription] = []
        self._seq = itertools.count(1)
        self.last_seq = 0
        # Identifies this numbering (see the module docstring); random, so a restarted
        # server is never taken for the one a client was following.
        self.boot = secrets.token_hex(8)
        self._recent: deque[BusMessage] = deque(maxlen=history)
        self._to_wake: dict[Subscription, None] = {}  # insertion-ordered set
        self._waker: asyncio.Task[None] | None = None

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
        self._to_wake.pop(subscription, None)

    def publish(self, message_type: str, data: dict[str, Any]) -> BusMessage:
        """Number the record and hand it to every subscriber without waiting."""
        self.last_seq = next(self._seq)
        message = BusMessage(self.last_seq, message_type, time.time(), data)
        self._recent.append(message)
        for subscription in tuple(self._subscribers):
            if subscription.offer(message):
                self._to_wake[subscription] = None
        self._wake_first_batch()
        return message

    def publish_sample(self, message_type: str, data: dict[str, Any]) -> BusMessage:
        """Hand a sample to the subscribers that asked for its type: no seq, not kept."""
        message = BusMessage(0, message_type, time.time(), data)
        for subscription in tuple(self._subscribers):
            if subscription.offer(message):
                self._to_wake[subscription] = None
        self._wake_first_batch()
        return message

    def since(self, seq: int) -> list[BusMessage] | None:
        """Every message published after `seq`, in order; None if some are no longer kept.

        The ring holds consecutive numbers (every publish appends), so it can fill
        the gap exactly when it still holds `seq + 1`. A `seq` at or beyond
        `last_seq` gives an empty list. Call it in the same turn of the loop as
        `subscribe`, so the two meet without a gap or an overlap.
        """
        if seq >= self.last_seq:
            return []
        if not self._recent or self._recent[0].seq > seq + 1:
            return None
        return list(itertools.islice(self._recent, seq + 1 - self._recent[0].seq, None))

    def _wake_first_batch(self) -> None:
        """Wake WAKE_BATCH subscribers now; a task wakes the rest, a batch per turn."""
        self._wake_batch()
        if not self._to_wake or (self._waker is not None and not self._waker.done()):
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a synchronous caller): nobody to interleave with
            while self._to_wake:
                self._wake_batch()
            return
        self._waker = loop.create_task(self._wake_the_rest(), name="bus-waker")

    async def _wake_the_rest(self) -> None:
        # Runs a turn after the publish; each turn, the loop polls its sockets first.
        while self._to_wake:
            self._wake_batch()
            await asyncio.sleep(0)

    def _wake_batch(self) -> None:
        for _ in range(min(WAKE_BATCH, len(self._to_wake))):
            subscription = next(iter(self._to_wake))
            del self._to_wake[subscription]
            subscription.wake()

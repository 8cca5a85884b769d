"""The one bus on which the worker publishes what happens in the cell.

Every message gets a sequence number that rises by one, so a subscriber can
tell whether it missed something. Publishing never waits: each subscriber has
a bounded buffer, and a subscriber that lets it fill up is closed with the
reason `slow consumer` instead of holding up the worker or anyone else. The
WebSocket hub and the metrics are subscribers; the journal is not (it must
never be dropped, so the worker hands it records directly).

Delivery is spread over turns of the event loop, starting on the turn after
the publish: with a thousand WebSocket clients, serving them all at once
would put a thousand sends in one turn (tens of milliseconds) ahead of
anything that arrives meanwhile, such as an e-stop request. Each turn serves
subscribers until a budget is spent: waking a subscriber's task costs
WAKE_COST, a message handed over directly costs one, and the budget is
DELIVERY_BUDGET (so WAKE_BATCH task wakes, or up to DELIVERY_BUDGET direct
hand-overs, a turn). The loop polls its sockets between turns.

A direct consumer (`Subscription.take_directly`) is how the WebSocket hub
skips the wake of one task per client and message: while the subscription's
task is waiting in `get` with nothing handed to it, the bus hands the
buffered messages to the consumer itself, which writes them to the client's
socket at once or says it cannot. What it refuses stays in the buffer and
the task is woken to take it the ordinary way; the consumer is not offered
another message until the task has emptied the buffer and waits again. So a
subscriber's messages leave its buffer in order, from its front, by one road
at a time: none is skipped, none twice. Offering stays at publish time, so
the slow-consumer rule and the types filter are the same for both roads.

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
import logging
import secrets
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

SLOW_CONSUMER = "slow consumer"
# Delivery work per turn of the loop. A direct hand-over (a socket write, about
# 10 µs on the 2-core bench machine) costs 1; waking a subscriber's task costs
# WAKE_COST (its send, about 30 µs, runs on the next turn, beside the next batch):
# 32 writes, or 16 wakes. A turn stays at a few tenths of a millisecond, and each
# hop of a stop request through the loop waits for one turn at most; 64 writes a
# turn makes the stop measurably slower with a thousand clients.
DELIVERY_BUDGET = 32
WAKE_COST = 2
WAKE_BATCH = DELIVERY_BUDGET // WAKE_COST  # subscribers' tasks woken per turn, at most
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


DirectConsumer = Callable[["BusMessage"], bool]
"""Takes one message at once (True), or cannot now (False): see `Subscription.take_directly`."""


class Subscription:
    """A bounded mailbox of bus messages for one consumer."""

    def __init__(self, bus: Bus, maxsize: int, types: Iterable[str] | None) -> None:
        self._bus = bus
        self._maxsize = maxsize
        self._buffer: deque[BusMessage] = deque()
        self._ready = asyncio.Event()
        self._waiting = False  # the consumer's task is suspended in `get`
        self.to_be_served = False  # in the bus's delivery queue (see `Bus._offer`)
        self._direct: DirectConsumer | None = None
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

    def take_directly(self, consumer: DirectConsumer | None) -> None:
        """Let the bus hand messages to `consumer` while this subscription's task waits.

        Why: waking one task per subscriber and message is most of a large
        fan-out's cost when all the task then does is one non-blocking write.
        `consumer` runs in the bus's delivery turn, must not block, and returns
        False when it cannot take the message now (the task then takes it, in
        order). None switches it off.
        """
        self._direct = consumer

    def offer(self, message: BusMessage) -> bool:
        """Queue a message (True), or close the subscription if its buffer is full.

        The consumer is not served here: the bus does that (see `Bus.publish`).
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

    def serve(self) -> int:
        """Hand the buffer to the direct consumer if it may have it, else wake the task.

        Returns the delivery cost spent (see the module docstring). The direct road
        is open only while the task waits in `get` and has not been woken: then it
        holds no message of its own, so nothing it sends can overtake or follow
        out of order what is handed over here.
        """
        self.to_be_served = False
        buffer, consumer = self._buffer, self._direct
        if self.closed_reason is not None:
            return 1
        if consumer is None or not self._waiting or self._ready.is_set():
            self.wake()
            return WAKE_COST
        handed = 0
        try:
            while buffer and consumer(buffer[0]):
                buffer.popleft()
                handed += 1
        except Exception:  # a bug in the consumer must not stop the other subscribers
            log.exception("direct delivery failed; this subscriber is served by its task")
            self._direct = None
        if buffer:
            self._ready.set()
            return handed + WAKE_COST
        return max(handed, 1)

    async def get(self) -> BusMessage:
        """The next message; raises SubscriptionClosed once closed (buffer discarded)."""
        while True:
            if self.closed_reason is not None:
                raise SubscriptionClosed(self.closed_reason)
            if self._buffer:
                return self._buffer.popleft()
            self._ready.clear()
            self._waiting = True
            try:
                await self._ready.wait()
            finally:
                self._waiting = False

    def close(self, reason: str = "closed") -> None:
        """Stop receiving; a waiting `get` raises SubscriptionClosed."""
        if self.closed_reason is None:
            self.closed_reason = reason
            self._buffer.clear()
            self._direct = None
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
        # Subscribers offered a message and not served since, oldest first. A deque
        # and a flag, not an ordered set: taking from the front of a dict rescans
        # what was taken before (quadratic in a thousand clients).
        self._to_serve: deque[Subscription] = deque()
        # The loop on which the next delivery turn is scheduled; None when none is.
        self._turn_loop: asyncio.AbstractEventLoop | None = None

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
        self._recent.append(message)
        self._offer(message)
        return message

    def publish_sample(self, message_type: str, data: dict[str, Any]) -> BusMessage:
        """Hand a sample to the subscribers that asked for its type: no seq, not kept."""
        message = BusMessage(0, message_type, time.time(), data)
        self._offer(message)
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

    def _offer(self, message: BusMessage) -> None:
        to_serve = self._to_serve
        for subscription in tuple(self._subscribers):
            if subscription.offer(message) and not subscription.to_be_served:
                subscription.to_be_served = True
                to_serve.append(subscription)
        self._schedule()

    def _schedule(self) -> None:
        """Serve the subscribers offered a message, from the next turn of the loop on."""
        if not self._to_serve:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a synchronous caller): nobody to interleave with
            while self._to_serve:
                self._serve_some()
            return
        # Compared by loop, not by a flag: a turn scheduled on a loop that has since
        # stopped never runs, and must not keep this bus from scheduling on the next.
        if self._turn_loop is not loop:
            self._turn_loop = loop
            loop.call_soon(self._serve_a_turn, loop)

    def _serve_a_turn(self, loop: asyncio.AbstractEventLoop) -> None:
        # A plain callback, not a task: between two turns the loop polls its sockets.
        self._turn_loop = None
        self._serve_some()
        if self._to_serve:
            self._turn_loop = loop
            loop.call_soon(self._serve_a_turn, loop)

    def _serve_some(self) -> None:
        budget, to_serve = DELIVERY_BUDGET, self._to_serve
        while budget > 0 and to_serve:
            budget -= to_serve.popleft().serve()  # a closed one costs little and is let go

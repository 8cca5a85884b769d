"""A bus subscription read with a run's progress thinned: at most one per interval.

Why: while a cell sprays, every waypoint publishes a `progress` record, and the
plant's interfaces would turn each one into work on the event loop (a CellState
write that asyncua's subscription loop then notifies; an MQTT message and its
QoS 1 exchange with the broker). An e-stop that arrives during one of those
callbacks waits for its end, so with both interfaces on the device stop while
spraying would be slower than on a plain cell (docs/benchmarks.md). The plant
needs to know where the run is, not each of its steps: like the HMI's device
feed (`device_push_interval`), the plant hears a run's progress at most once
per `plant_progress_interval`, the latest kept.

The rules, so the plant loses nothing it was promised:

- a progress record that comes at least `interval` after the last one handed
  on goes at once (a run's first waypoint is never held);
- one that comes sooner is held, replacing any record still held (the latest
  wins), and is handed on when its interval has passed;
- any other record (a transition, a fault, an alert) is never held: a record
  still held goes just before it, so the order is kept and the transition that
  ends a run always follows the run's final progress;
- only progress that reports where the run is (a waypoint or a fraction) is
  thinned; a recovery attempt's record passes like a transition.

`interval` 0 hands on every record as it comes.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

from server.core.infra.bus import BusMessage, Subscription


def is_paced(message: BusMessage) -> bool:
    """Whether a record is a run's progress, which may be thinned."""
    data = message.data
    return message.type == "progress" and ("waypoint" in data or "fraction" in data)


class PacedFeed:
    """The records of one bus subscription, progress at most once per `interval`."""

    def __init__(
        self,
        subscription: Subscription,
        interval: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.subscription = subscription
        self.interval = interval
        self._clock = clock
        self._held: BusMessage | None = None  # the latest progress not yet handed on
        self._after: BusMessage | None = None  # the record that made the held one go
        self._last = -math.inf  # when the last progress was handed on
        self.thinned = 0  # progress records replaced by a newer one before they went

    def resubscribe(self, subscription: Subscription) -> None:
        """A new subscription after a catch-up: nothing held carries over (the reader
        starts again from the cell's present)."""
        self.subscription = subscription
        self._held = self._after = None

    async def get(self) -> BusMessage:
        """The next record to act on; raises SubscriptionClosed as the subscription does."""
        if self._after is not None:
            message, self._after = self._after, None
            return message
        while True:
            if self._held is not None and not self.subscription.pending and self._due_in() <= 0:
                return self._hand_on_held()
            received = await self._receive()
            if received is None:  # the held progress's interval has passed
                return self._hand_on_held()
            message = received
            if not is_paced(message):
                if self._held is None:
                    return message
                self._after = message
                return self._hand_on_held()
            if self._held is None and self._due_in() <= 0:
                self._last = self._clock()
                return message
            if self._held is not None:
                self.thinned += 1
            self._held = message

    def _due_in(self) -> float:
        return self._last + self.interval - self._clock()

    async def _receive(self) -> BusMessage | None:
        """The next record; None when a progress is held and its time came first."""
        if self._held is None or self.subscription.pending:
            return await self.subscription.get()
        try:
            return await asyncio.wait_for(self.subscription.get(), self._due_in())
        except TimeoutError:
            return None

    def _hand_on_held(self) -> BusMessage:
        held, self._held = self._held, None
        assert held is not None
        self._last = self._clock()
        return held

"""The bounded, prioritised queue the worker drains.

Three lanes, drained in order: emergency stops, faults, everything else.
Within a lane, arrival order holds. Only the request lane is bounded by
event_queue_size, because that is where the outside world can pile work on:
when it is full the request is refused with EventQueueFull, never dropped.
Emergency stops and device faults are never refused; their lanes are small by
nature (a handful of devices, and an e-stop that is already queued makes a
second one redundant, so consecutive e-stops are still each answered but cost
nothing extra to decide).
"""

from __future__ import annotations

import asyncio
import itertools
import secrets
import time
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import TYPE_CHECKING

from server.common.errors import EventQueueFull
from server.core.machine.transitions import Event

if TYPE_CHECKING:
    from server.core.machine.events import AuditNote, Outcome, Payload
    from server.core.worker.context import RunningOperation
    from server.core.worker.devices import HaltReport


class Priority(IntEnum):
    """Lower drains first."""

    EMERGENCY = 0
    FAULT = 1
    REQUEST = 2


@dataclass(slots=True)
class Envelope:
    """One event on its way to the worker, with the future its sender awaits."""

    event_id: str
    event: Event
    source: str
    payload: Payload
    priority: Priority
    enqueued_at: float = field(default_factory=time.perf_counter)
    timestamp: float = field(default_factory=time.time)
    future: asyncio.Future[Outcome] | None = None
    audit: AuditNote | None = None  # who sent it: its audit row goes into the event's commit
    # A command's e-stops counted when it reached its door (decide.py's "asked before a stop")
    asked_at_estops: int | None = None
    # An e-stop's halt, made before it was queued: its transition's first HALT is this one.
    halt_made: asyncio.Future[HaltReport] | None = None
    # The operation this event's transition cancelled (CANCEL_RUN runs before
    # RECORD_FAULT): the fault's record names what it interrupted.
    interrupted: RunningOperation | None = None


class EventIds:
    """The id of each event put on one worker's queue: this boot's prefix and a sequence.

    Shared by the two ways onto the queue (`posting.py: EventPoster` and the e-stop's
    `stop.py: Stop.post`), so every event of a boot has a distinct id in logs and the
    journal; the prefix tells one boot's events from another's.
    """

    def __init__(self) -> None:
        self._boot = secrets.token_hex(3)
        self._sequence = itertools.count(1)

    def next(self) -> str:
        return f"{self._boot}-{next(self._sequence):06d}"


class EventQueue:
    """Priority lanes; the request lane holds at most `capacity` envelopes."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._lanes: dict[Priority, deque[Envelope]] = {p: deque() for p in Priority}
        self._in_order = tuple(self._lanes[p] for p in sorted(Priority))  # drained in this order
        self._ready = asyncio.Event()

    def __len__(self) -> int:
        return sum(len(lane) for lane in self._lanes.values())

    def put(self, envelope: Envelope, *, bounded: bool = True) -> None:
        """Queue an envelope; a full request lane raises EventQueueFull when `bounded`."""
        lane = self._lanes[envelope.priority]
        if bounded and envelope.priority is Priority.REQUEST and len(lane) >= self.capacity:
            raise EventQueueFull(self.capacity)
        lane.append(envelope)
        self._ready.set()

    async def get(self) -> Envelope:
        """The next envelope, highest priority first."""
        while True:
            for lane in self._in_order:
                if lane:
                    return lane.popleft()
            self._ready.clear()
            await self._ready.wait()

    def drain(self) -> list[Envelope]:
        """Remove and return everything queued (used at shutdown)."""
        envelopes = [env for priority in Priority for env in self._lanes[priority]]
        for lane in self._lanes.values():
            lane.clear()
        return envelopes

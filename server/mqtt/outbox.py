"""What waits for the broker: bounded, in order, the latest of each retained topic kept.

Why two kinds of entry: the stream topics (event, progress, alert, run) are a
history, each message counts, so while the broker is away they are kept up to
a bound and the oldest is dropped beyond it, counted; the retained topics
(status, state, kpis, health) are a present, only the latest matters, so a
newer one replaces the one still waiting. A retained entry is therefore never
dropped, and what the broker holds after a reconnect is always the latest
state however long it was away. Order is kept across both kinds, so a
subscriber sees a transition's state and event in the order they happened.

A run's progress entries name their run, so the link drops those of runs that
have ended when the broker comes back (`discard_progress`). Pure: no I/O, no
clock; the link (`link.py`) takes entries out and puts one back at the front
when its publish failed.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Entry:
    """One MQTT publication: topic, payload, and whether the broker keeps it."""

    topic: str
    payload: bytes
    retain: bool = False
    run_id: str | None = None  # a run's progress: whose (stale once that run has ended)


class Outbox:
    """A bounded, ordered queue of entries for one broker connection."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._entries: deque[Entry] = deque()
        self._stream = 0  # how many entries are stream (non-retained) ones
        self._ready = asyncio.Event()
        self.dropped = 0  # stream messages dropped since start (oldest first)

    def __len__(self) -> int:
        return len(self._entries)

    def put(self, entry: Entry) -> None:
        """Queue an entry; a retained one replaces its topic's older one still waiting."""
        if entry.retain:
            for old in self._entries:
                if old.retain and old.topic == entry.topic:
                    self._entries.remove(old)
                    break
        else:
            self._stream += 1
        self._entries.append(entry)
        while self._stream > self.limit:
            self._drop_oldest_stream()
        self._ready.set()

    def put_back(self, entry: Entry) -> None:
        """Return an entry whose publish failed to the front, unless a newer one replaced it."""
        if entry.retain and any(e.retain and e.topic == entry.topic for e in self._entries):
            return
        self._entries.appendleft(entry)
        if not entry.retain:
            self._stream += 1
            while self._stream > self.limit:
                self._drop_oldest_stream()
        self._ready.set()

    def take(self) -> Entry | None:
        """The oldest entry, removed; None when empty."""
        if not self._entries:
            self._ready.clear()
            return None
        entry = self._entries.popleft()
        if not entry.retain:
            self._stream -= 1
        return entry

    def discard_progress(self, keep_run: str | None) -> int:
        """Drop the progress waiting of every run but `keep_run` (the one under way, if
        any); how many. Why: after an outage, a run that has ended is told by its `run`
        message and the transitions; its waypoints would only replay a past that a
        subscriber would take for the present. Not counted as dropped: nothing is lost."""
        stale = [e for e in self._entries if e.run_id is not None and e.run_id != keep_run]
        for entry in stale:
            self._entries.remove(entry)
            self._stream -= 1
        return len(stale)

    async def wait(self) -> None:
        """Until there is something to take."""
        while not self._entries:
            self._ready.clear()
            await self._ready.wait()

    def _drop_oldest_stream(self) -> None:
        for entry in self._entries:
            if not entry.retain:
                self._entries.remove(entry)
                self._stream -= 1
                self.dropped += 1
                return

"""Time as a parameter: the worker, supervision and the pause gate read it from a Clock.

Why: a unit test of a 30 s budget or a 5 s ERROR alert should take
milliseconds, not 30 s. Production code uses `SYSTEM_CLOCK`; tests hand in a
clock whose `sleep` advances virtual time at once (see tests/fakes.py).

`call_later` is the cheap form of a wait whose only purpose is to do one
thing later (the ERROR alert, a run's time budget): a timer on the loop, not a
task that sleeps, so the worker's hot path creates no task for it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Protocol


class Timer(Protocol):
    """A callback scheduled by `Clock.call_later`; cancelling it means it never runs."""

    def cancel(self) -> None: ...


class Clock(Protocol):
    """Wall time for records, a monotonic clock for durations, and a way to wait."""

    def time(self) -> float:
        """Seconds since the epoch (what records and messages show)."""
        ...

    def monotonic(self) -> float:
        """Seconds on a clock that never goes back (what durations are measured on)."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Wait `seconds` of this clock's time."""
        ...

    def call_later(self, seconds: float, callback: Callable[[], None]) -> Timer:
        """Call `callback` on the running loop once `seconds` of this clock's time passed."""
        ...


class SystemClock:
    """The real clock."""

    def time(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    def call_later(self, seconds: float, callback: Callable[[], None]) -> Timer:
        return asyncio.get_running_loop().call_later(seconds, callback)


SYSTEM_CLOCK: Clock = SystemClock()

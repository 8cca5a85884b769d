"""Time as a parameter: the worker, supervision and the pause gate read it from a Clock.

Why: a unit test of a 30 s budget or a 5 s ERROR alert should take
milliseconds, not 30 s. Production code uses `SYSTEM_CLOCK`; tests hand in a
clock whose `sleep` advances virtual time at once (see tests/fakes.py).
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


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


class SystemClock:
    """The real clock."""

    def time(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)


SYSTEM_CLOCK: Clock = SystemClock()

"""The event loop's lag: how late a task that asked to sleep wakes up.

Why: a loop held up by blocking work delays every answer and the e-stop's own request
handling; its lag is the first sign. A small task of its own sleeps `interval`, and the
overshoot is the lag. It only measures (never on the worker's path); the watch reads the
largest lag since its last look.
"""

from __future__ import annotations

import asyncio
import contextlib
import time


class LoopLag:
    """Samples the running loop's lag until stopped."""

    def __init__(self, interval: float) -> None:
        self.interval = interval
        self.last_s = 0.0
        self.max_s = 0.0  # the largest since `take_max`
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self._sample(), name="loop-lag")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    def take_max(self) -> float:
        """The largest lag since the last call (then starts again from the latest)."""
        worst, self.max_s = self.max_s, self.last_s
        return worst

    async def _sample(self) -> None:
        while True:
            asked = time.monotonic()
            await asyncio.sleep(self.interval)
            self.last_s = max(0.0, time.monotonic() - asked - self.interval)
            self.max_s = max(self.max_s, self.last_s)

"""The commands whose answers are still on their way, and a wait for none to be.

Why: the plant's interfaces (the MQTT link, the OPC UA follower) turn each
transition into messages and tags. That work runs on the event loop, under
the interpreter lock, at the very moment the command that made the transition
(an e-stop above all) is being answered, and would add milliseconds to the
stop's answer on a cell serving both. Waiting for the transition's commit is
not enough: the answer still takes a few hops of the loop after it (the
route's return, the response's encoding, the write), and the interfaces' work
would run between them. So the interfaces wait until no command's answer is in
flight: the plant hears a transition a little later; the stop is not
answered later.

The wait is bounded (`limit`): a steady stream of commands must not keep the
plant uninformed. A request counts from its arrival at the app to the end of
its response; only commands count (not GET, HEAD or OPTIONS: a dashboard
polling /state must not hold the plant back).
"""

from __future__ import annotations

import asyncio
import contextlib

READS = frozenset({"GET", "HEAD", "OPTIONS"})
DEFAULT_LIMIT_S = 0.05  # the longest the plant waits behind answers, per wait


class AnswersInFlight:
    """A count of commands being answered, and a wait for it to reach zero."""

    def __init__(self) -> None:
        self._count = 0
        self._none = asyncio.Event()
        self._none.set()

    @property
    def count(self) -> int:
        return self._count

    def begin(self) -> None:
        """A command arrived: its answer is now on its way."""
        self._count += 1
        self._none.clear()

    def end(self) -> None:
        """The command's answer was written (or failed)."""
        self._count = max(0, self._count - 1)
        if self._count == 0:
            self._none.set()

    async def none_pending(self, limit: float = DEFAULT_LIMIT_S) -> None:
        """Return once no answer is in flight, or after `limit` seconds anyway."""
        if self._count == 0:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._none.wait(), limit)


async def after_answers(answers: AnswersInFlight | None) -> None:
    """What the interfaces await before their work for a transition (None: no wait)."""
    if answers is not None:
        await answers.none_pending()

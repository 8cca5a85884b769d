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

Only the answers already on their way when the interface starts to wait are
waited for: a command that arrives after the transition (the reset an operator
presses right after a stop) is not the one whose answer the transition's
messages would slow, and waiting for it would keep the plant uninformed of the
stop for as long as the reset takes.

The wait is bounded (`limit`): a steady stream of commands must not keep the
plant uninformed. A request counts from its arrival at the app to the end of
its response; only commands count (not GET, HEAD or OPTIONS: a dashboard
polling /state must not hold the plant back).
"""

from __future__ import annotations

import asyncio

READS = frozenset({"GET", "HEAD", "OPTIONS"})
DEFAULT_LIMIT_S = 0.05  # the longest the plant waits behind answers, per wait


class AnswersInFlight:
    """The commands being answered, each by its ticket, and waits for those begun so far."""

    def __init__(self) -> None:
        self._begun = 0  # tickets handed out so far; each ticket is the count at its begin
        self._open: dict[int, None] = {}  # tickets not yet ended, oldest first
        self._waiters: list[tuple[int, asyncio.Future[None]]] = []

    @property
    def count(self) -> int:
        return len(self._open)

    def begin(self) -> int:
        """A command arrived: its answer is now on its way. Its ticket, for `end`."""
        self._begun += 1
        self._open[self._begun] = None
        return self._begun

    def end(self, ticket: int) -> None:
        """The command's answer was written (or failed); ending a ticket twice is harmless."""
        if self._open.pop(ticket, False) is False or not self._waiters:
            return
        oldest = next(iter(self._open), self._begun + 1)
        still = []
        for mark, waiter in self._waiters:
            if mark < oldest:
                if not waiter.done():
                    waiter.set_result(None)
            else:
                still.append((mark, waiter))
        self._waiters = still

    async def none_pending(self, limit: float = DEFAULT_LIMIT_S) -> None:
        """Return once every answer in flight now has gone, or after `limit` s anyway."""
        if not self._open:
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        entry = (self._begun, waiter)
        self._waiters.append(entry)
        try:
            await asyncio.wait_for(waiter, limit)
        except TimeoutError:
            pass
        finally:
            if entry in self._waiters:
                self._waiters.remove(entry)


async def after_answers(answers: AnswersInFlight | None) -> None:
    """What the interfaces await before their work for a transition (None: no wait)."""
    if answers is not None:
        await answers.none_pending()

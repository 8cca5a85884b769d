"""A coroutine's first step run at once: in the task that goes on to await the rest
(`Started`), or as a task of its own (`start_task`).

Why: the worker's halt, a pause's hold and a reset's probe each command several
devices "at once", which costs a task per command. A command that answers
without waiting (a device that needs no round trip, a fake) then pays a task
and a loop turn for nothing. Python 3.12's eager tasks solve this for tasks;
3.11 has none. `Started(coro)` runs the first step now: if it finished, its
result is there without a task; if it is waiting, the caller decides what
else to start before it awaits the rest (see `CellDevices.safe_halt`).

The one rule that makes this safe: **the rest is awaited in the same task that
ran the first step**, never handed to another one. The first step may bind
itself to the current task (`asyncio.timeout` does, to cancel it later), and
awaiting the rest here keeps that binding true. Awaiting a `Started` then
behaves exactly like `await coro`: the same futures reach the task, and a
cancellation is thrown into the coroutine where it waits.

When the caller must not wait at all (the e-stop's halt), `start_task(coro)`
is the eager task 3.12 has and 3.11 lacks: a task whose first step has run,
as that task, by the time it is returned.
"""

from __future__ import annotations

import asyncio
import contextvars
import sys
from collections.abc import Coroutine, Generator
from typing import Any, Generic, TypeVar

T = TypeVar("T")
_EAGER_START = sys.version_info >= (3, 12)  # asyncio.Task(..., eager_start=True)


class Started(Generic[T]):
    """`coro` with its first step already run in the current task; await it for the rest."""

    __slots__ = ("_coro", "_error", "_pending", "_result", "done")

    def __init__(self, coro: Coroutine[Any, Any, T]) -> None:
        self._coro = coro
        self._pending: Any = None  # what the coroutine waits on (a future, or None: a bare yield)
        self._result: T | None = None
        self._error: BaseException | None = None
        self.done = True  # finished in its first step (with a result or an exception)
        try:
            self._pending = coro.send(None)
        except StopIteration as stop:
            self._result = stop.value
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:  # CancelledError included: the coroutine's own outcome
            self._error = exc
        else:
            self.done = False

    def close(self) -> None:
        """Abandon a coroutine still waiting (its `finally` blocks run now)."""
        if not self.done:
            self.done = True
            self._coro.close()

    def __await__(self) -> Generator[Any, Any, T]:
        if self.done:
            if self._error is not None:
                raise self._error
            return self._result  # type: ignore[return-value]
        self.done = True  # awaited once: from here the coroutine runs in this task
        return (yield from _drive(self._coro, self._pending))


def start_task(coro: Coroutine[Any, Any, T]) -> asyncio.Task[T]:
    """A task of `coro` whose first step has already run, as that task, when this returns.

    Why: the e-stop's halt commands are tasks, because the stop must not wait
    for their answers. A task's first step waits for the loop's next turn,
    behind every callback already ready (a crowd's WebSocket writes, a vision
    result, the requests queued ahead): the stop's frames then left up to a few
    ms after it arrived. Started here, each command's frame is written before
    this returns. Python 3.12 calls this an eager task (`eager_start=True`); on
    3.11 the first step runs here with the new task made the current one, so
    whatever the step binds to its task (asyncio.timeout, a lock's owner) is
    bound to the task that drives the rest, and in the task's own context.
    """
    loop = asyncio.get_running_loop()
    if _EAGER_START:
        return asyncio.Task(coro, loop=loop, eager_start=True)  # type: ignore[call-arg]
    context = contextvars.copy_context()
    first = _FirstStepDone(coro)
    task = loop.create_task(first, name=getattr(coro, "__qualname__", None), context=context)
    outer = asyncio.current_task(loop)
    if outer is not None:
        asyncio.tasks._leave_task(loop, outer)
    try:
        asyncio.tasks._enter_task(loop, task)
        try:
            context.run(first.step)
        except BaseException:  # KeyboardInterrupt, SystemExit: the task must not go on
            task.cancel()
            raise
        finally:
            asyncio.tasks._leave_task(loop, task)
    finally:
        if outer is not None:
            asyncio.tasks._enter_task(loop, outer)
    return task


class _FirstStepDone(Coroutine[Any, Any, T]):
    """What `start_task`'s task drives: `coro`, whose first step `step` ran beforehand.

    The task's own first step receives what that step gave (the future it waits
    on, its result or its exception); from then on each resumption and each
    exception (a cancellation) goes straight to `coro`. Until then the future is
    not marked as awaited (so another task may await it meanwhile), and a cancel
    that reaches the task first cancels that future and is thrown into `coro`
    where it waits, as a task's cancel does: the coroutine's own handling runs.
    """

    __slots__ = ("_coro", "_outcome", "_stepped")

    def __init__(self, coro: Coroutine[Any, Any, T]) -> None:
        self._coro = coro
        self._stepped = False
        self._outcome: tuple[str, Any] = ("yield", None)

    def step(self) -> None:
        try:
            waits_on = self._coro.send(None)
        except StopIteration as stop:
            self._outcome = ("return", stop.value)
        except (KeyboardInterrupt, SystemExit) as exc:
            self._outcome = ("interrupted", exc)  # finished: a cancel can only end the task
            raise
        except BaseException as exc:  # CancelledError included: the coroutine's own outcome
            self._outcome = ("raise", exc)
        else:
            # A future is awaited by the task it is handed to: the flag goes back on
            # when it is handed over, on the task's first turn.
            if getattr(waits_on, "_asyncio_future_blocking", False):
                waits_on._asyncio_future_blocking = False
            self._outcome = ("yield", waits_on)

    def _take_outcome(self) -> tuple[str, Any]:
        self._stepped = True
        outcome, self._outcome = self._outcome, ("yield", None)  # no reference kept
        return outcome

    def send(self, value: Any) -> Any:
        if self._stepped:
            return self._coro.send(value)
        kind, what = self._take_outcome()
        if kind == "yield":
            if hasattr(what, "_asyncio_future_blocking"):
                what._asyncio_future_blocking = True
            return what
        if kind == "return":
            raise StopIteration(what)
        raise what

    def throw(self, typ: Any, val: Any = None, tb: Any = None) -> Any:
        exc = typ if val is None else val
        if self._stepped:
            return self._coro.throw(exc)
        kind, what = self._take_outcome()
        if kind == "return":  # finished already: its outcome stands, the throw comes too late
            raise StopIteration(what)
        if kind == "raise":
            raise what
        if kind == "interrupted":
            raise exc
        if isinstance(exc, asyncio.CancelledError) and isinstance(what, asyncio.Future):
            what.cancel()  # what a task's cancel does to the future it waits on
        return self._coro.throw(exc)

    def close(self) -> None:
        self._coro.close()

    def __await__(self) -> Generator[Any, Any, T]:
        raise TypeError("a started task's coroutine is driven by its task only")


def _drive(coro: Coroutine[Any, Any, T], pending: Any) -> Generator[Any, Any, T]:
    """`await coro` from where its first step left it waiting on `pending`.

    What `yield from` does, except that the first value is already known: each
    resumption is sent in, each exception (a cancellation) thrown in.
    """
    while True:
        try:
            sent = yield pending
        except GeneratorExit:
            coro.close()
            raise
        except BaseException as exc:
            try:
                pending = coro.throw(exc)
            except StopIteration as stop:
                return stop.value  # type: ignore[no-any-return]
        else:
            try:
                pending = coro.send(sent)
            except StopIteration as stop:
                return stop.value  # type: ignore[no-any-return]


async def within(call: Coroutine[Any, Any, T], timeout: float) -> T:
    """Await `call` for at most `timeout` s (TimeoutError after); the timer is set only
    if `call` has to wait.

    Why: a command that answers in its first step cannot be late, and arming and
    cancelling a timer for it is a good part of what a halt costs on devices that
    answer at once. The first step runs in this task and so does the rest, under
    asyncio.timeout (not asyncio.wait_for, which on 3.11 can lose a cancel).
    """
    started = Started(call)
    if started.done:
        return await started
    async with asyncio.timeout(timeout):
        return await started


async def together(calls: list[Coroutine[Any, Any, T]]) -> list[T]:
    """The results of `calls`, run at once (none waits for another), in their order.

    Like asyncio.gather, except that a call answering in its first step costs no
    task: each is started here in turn while they answer at once; the first that
    has to wait goes on in this task, and every later one as a task of its own.
    If this task is cancelled, the calls still running are cancelled too.
    """
    results: list[T] = []
    for index, call in enumerate(calls):
        started = Started(call)
        if started.done:
            results.append(await started)
            continue
        rest = [asyncio.ensure_future(later) for later in calls[index + 1 :]]
        try:
            results.append(await started)
        except BaseException:
            for task in rest:
                task.cancel()
            raise
        results.extend(await asyncio.gather(*rest))
        break
    return results

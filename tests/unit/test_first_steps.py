"""Commands that answer at once cost no task (server/core/infra/eager.py), and nothing else changes.

The halt still puts the valve's close first and lets neither command wait for
the other's answer; a pause still cancels a move on the spot while the run goes
on; a cancel that lands with the pause is still never swallowed.
"""

from __future__ import annotations

import asyncio
import contextvars
import gc
from typing import Any

from server.core.infra.eager import Started, start_task
from server.core.operations.base import PauseGate
from server.core.worker.devices import CellDevices
from server.core.worker.stop import halt_at_once
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


async def _turns(count: int = 5) -> None:
    for _ in range(count):
        await asyncio.sleep(0)


async def _ask(reply: asyncio.Future[str], seen: list[Any]) -> str:
    """Note the task it runs in before and after it waits for `reply`."""
    seen.append(asyncio.current_task())
    answer = await reply
    seen.append(asyncio.current_task())
    return answer


async def test_a_coroutine_that_answers_at_once_is_done_without_a_task() -> None:
    async def answer() -> int:
        return 42

    before = len(asyncio.all_tasks())
    started = Started(answer())
    assert started.done and len(asyncio.all_tasks()) == before
    assert await started == 42


async def test_a_coroutine_that_waits_goes_on_in_the_awaiting_task() -> None:
    reply: asyncio.Future[str] = asyncio.get_running_loop().create_future()
    seen: list[Any] = []

    started = Started(_ask(reply, seen))
    assert not started.done
    asyncio.get_running_loop().call_soon(reply.set_result, "ok")
    assert await started == "ok"
    assert seen == [asyncio.current_task()] * 2  # both steps in this task, none in another


async def test_a_cancel_reaches_the_coroutine_where_it_waits() -> None:
    cleaned: list[str] = []

    async def wait_forever() -> None:
        try:
            await asyncio.sleep(3600)
        finally:
            cleaned.append("finally")

    async def holder() -> None:
        await Started(wait_forever())

    task = asyncio.create_task(holder())
    await _turns()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert task.cancelled() and cleaned == ["finally"]


async def test_an_exception_of_the_first_step_is_raised_when_awaited() -> None:
    async def fail() -> None:
        raise RuntimeError("no link")

    started = Started(fail())
    assert started.done
    try:
        await started
    except RuntimeError as exc:
        assert str(exc) == "no link"
    else:
        raise AssertionError("the first step's exception was lost")


async def test_a_started_task_has_run_its_first_step_as_itself_when_made() -> None:
    reply: asyncio.Future[str] = asyncio.get_running_loop().create_future()
    seen: list[Any] = []

    outer = asyncio.current_task()
    task = start_task(_ask(reply, seen))
    assert seen == [task]  # before any turn of the loop, and as the new task
    assert asyncio.current_task() is outer  # this task is the current one again
    reply.set_result("ok")
    assert await task == "ok"
    assert seen == [task, task]


async def test_a_started_task_that_answers_at_once_has_its_result() -> None:
    async def answer() -> int:
        return 42

    async def fail() -> None:
        raise RuntimeError("no link")

    assert await start_task(answer()) == 42
    failing = start_task(fail())
    await asyncio.gather(failing, return_exceptions=True)
    assert isinstance(failing.exception(), RuntimeError)


async def test_a_timeout_entered_in_the_first_step_ends_the_started_task_only() -> None:
    """asyncio.timeout binds to the task current at its entry: it must be the new one."""

    async def late() -> str:
        try:
            async with asyncio.timeout(0.01):
                await asyncio.sleep(3600)
        except TimeoutError:
            return "timed out"
        return "not timed out"

    task = start_task(late())
    assert await task == "timed out"
    await _turns()  # this task, the one that made it, was not cancelled meanwhile


async def test_a_cancel_before_the_started_tasks_first_turn_reaches_the_coroutine() -> None:
    cleaned: list[str] = []

    async def wait_forever() -> None:
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            cleaned.append("cancelled where it waits")
            raise

    task = start_task(wait_forever())
    task.cancel()  # the loop has not turned: the task's own first step is still to come
    await asyncio.gather(task, return_exceptions=True)
    assert task.cancelled() and cleaned == ["cancelled where it waits"]


async def test_a_future_a_started_task_waits_on_may_be_awaited_by_another_meanwhile() -> None:
    shared: asyncio.Future[int] = asyncio.get_running_loop().create_future()

    async def wait() -> int:
        return await shared

    # Each waits on `shared` before the other's task has had a turn.
    first, second = start_task(wait()), start_task(wait())
    plain = asyncio.ensure_future(wait())
    await asyncio.sleep(0)
    shared.set_result(1)
    assert await asyncio.gather(first, second, plain) == [1, 1, 1]


async def test_a_cancel_before_the_first_turn_cancels_what_the_task_waits_on() -> None:
    inner = asyncio.ensure_future(asyncio.sleep(3600))

    async def wait() -> None:
        await inner

    task = start_task(wait())
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert task.cancelled() and inner.cancelled()  # as a task's cancel does


async def test_a_first_step_interrupted_leaves_its_task_cancelled() -> None:
    async def interrupted() -> None:
        raise KeyboardInterrupt

    made: list[asyncio.Task[None]] = []
    create_task = asyncio.get_running_loop().create_task

    def keep(coro: Any, **kwargs: Any) -> asyncio.Task[Any]:
        made.append(create_task(coro, **kwargs))
        return made[-1]

    loop = asyncio.get_running_loop()
    loop.create_task = keep  # type: ignore[method-assign]
    try:
        start_task(interrupted())
    except KeyboardInterrupt:
        pass
    else:
        raise AssertionError("the interrupt was swallowed")
    finally:
        del loop.create_task
    await asyncio.gather(*made, return_exceptions=True)
    assert made[0].cancelled()


async def test_a_started_task_runs_in_a_context_of_its_own() -> None:
    where = contextvars.ContextVar("where", default="outside")

    async def mark() -> str:
        where.set("inside")
        await asyncio.sleep(0)
        return where.get()

    assert await start_task(mark()) == "inside"
    assert where.get() == "outside"


class _SlowValve(FakeGlue):
    """A valve whose close waits for its answer until the test gives it."""

    def __init__(self, log: list[str]) -> None:
        super().__init__()
        self.log = log
        self.answer: asyncio.Event = asyncio.Event()

    async def set_valve(self, open_: bool) -> None:
        self.log.append("valve sent")
        await self.answer.wait()
        self.log.append("valve answered")


class _LoggingRobot(FakeRobot):
    def __init__(self, log: list[str]) -> None:
        super().__init__()
        self.log = log

    async def stop(self) -> None:
        self.log.append("stop sent")
        await super().stop()


async def test_the_halt_sends_the_stop_while_the_valve_waits_for_its_answer() -> None:
    log: list[str] = []
    glue = _SlowValve(log)
    devices = CellDevices(_LoggingRobot(log), glue, FakeCamera())
    halt = asyncio.create_task(devices.safe_halt(1.0, then=lambda: log.append("then")))
    await _turns()
    assert log == ["valve sent", "stop sent", "then"]  # valve first, the stop not held back
    glue.answer.set()
    report = await halt
    assert report.valve_closed and report.robot_stopped and not report.errors


async def test_the_stops_halt_has_sent_both_commands_when_made() -> None:
    log: list[str] = []
    glue = _SlowValve(log)
    halt = halt_at_once(CellDevices(_LoggingRobot(log), glue, FakeCamera()), 1.0)
    assert log == ["valve sent", "stop sent"]  # valve first, before the loop turned
    glue.answer.set()
    report = await halt
    assert report.valve_closed and report.robot_stopped and not report.errors


async def test_no_garbage_collection_starts_while_the_stops_frames_are_written() -> None:
    seen: list[bool] = []

    class Watching(FakeGlue):
        async def set_valve(self, open_: bool) -> None:
            seen.append(gc.isenabled())
            await super().set_valve(open_)

    class WatchingRobot(FakeRobot):
        async def stop(self) -> None:
            seen.append(gc.isenabled())
            await super().stop()

    assert gc.isenabled()
    report = await halt_at_once(CellDevices(WatchingRobot(), Watching(), FakeCamera()), 1.0)
    assert seen == [False, False] and gc.isenabled()  # off for the first steps only
    assert report.valve_closed and report.robot_stopped


async def test_the_halt_of_devices_that_answer_at_once_makes_no_task() -> None:
    log: list[str] = []
    devices = CellDevices(_LoggingRobot(log), FakeGlue(), FakeCamera())
    before = len(asyncio.all_tasks())
    report = await devices.safe_halt(
        1.0, then=lambda: log.append(f"tasks {len(asyncio.all_tasks())}")
    )
    assert log == ["stop sent", f"tasks {before}"]
    assert report.valve_closed and report.robot_stopped


async def _move_in(gate: PauseGate, moving: asyncio.Event) -> str:
    async with gate.interruption() as stretch:
        moving.set()
        await asyncio.sleep(3600)
    return "interrupted" if stretch.interrupted else "ended"


async def test_a_pause_interrupts_the_move_and_the_run_goes_on() -> None:
    gate, moving = PauseGate(), asyncio.Event()
    run = asyncio.create_task(_move_in(gate, moving))
    await moving.wait()
    gate.pause()
    assert await asyncio.wait_for(run, 1) == "interrupted"
    assert run.cancelling() == 0  # the pause's cancel is spent, nothing left pending


async def test_a_cancel_landing_with_the_pause_is_not_swallowed() -> None:
    gate, moving = PauseGate(), asyncio.Event()
    run = asyncio.create_task(_move_in(gate, moving))
    await moving.wait()
    gate.pause()
    run.cancel()  # the run is cancelled in the same turn as the pause
    await asyncio.gather(run, return_exceptions=True)
    assert run.cancelled()


async def test_after_the_block_a_pause_leaves_the_task_alone() -> None:
    gate, moving = PauseGate(), asyncio.Event()
    assert await asyncio.wait_for(_after_block(gate, moving), 1) == "not cancelled"


async def _after_block(gate: PauseGate, moving: asyncio.Event) -> str:
    async with gate.interruption():
        moving.set()
    gate.pause()
    await _turns()
    return "not cancelled"


async def test_a_run_cancelled_before_its_first_step_is_not_waited_for(
    make_worker: Any, fast_settings: Settings
) -> None:
    """Its `finally` never runs, so the end is told by the task's done callback instead."""
    worker = await make_worker(fast_settings.model_copy(update={"emergency_stop_timeout": 30.0}))
    worker.runs.start("calibrate_robot", "run-early", {})
    # cancelled in the same turn it was created (asyncio.timeout, not wait_for, which
    # would run cancel() in a task of its own, a turn later): not the 30 s timeout
    async with asyncio.timeout(5):
        await worker.runs.cancel()

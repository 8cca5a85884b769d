"""The pause gate's steps: what the worker waits for before it reports PAUSED."""

from __future__ import annotations

import asyncio

from server.core.operations.base import PauseGate


async def _turns(n: int = 5) -> None:
    for _ in range(n):
        await asyncio.sleep(0)


async def test_settled_waits_for_the_step_in_progress_and_not_for_the_held_one() -> None:
    gate = PauseGate()
    inside, leave = asyncio.Event(), asyncio.Event()

    async def run() -> list[str]:
        done = []
        async with gate.step():
            inside.set()
            await leave.wait()  # a move under way
            done.append("first")
        async with gate.step():  # waits at the gate while paused
            done.append("second")
        return done

    task = asyncio.create_task(run())
    await inside.wait()
    gate.pause()
    settled = asyncio.create_task(gate.settled())
    await _turns()
    assert not settled.done(), "a step in progress: the run may still move or spray"
    leave.set()
    await asyncio.wait_for(settled, 1)
    await _turns()
    assert gate.holding and not task.done()
    gate.resume()
    assert await asyncio.wait_for(task, 1) == ["first", "second"]


async def test_a_pause_outside_any_step_is_settled_at_once() -> None:
    gate = PauseGate()
    gate.pause()
    await asyncio.wait_for(gate.settled(), 1)


async def test_a_pause_cancels_the_move_in_progress_on_the_spot() -> None:
    gate, moving = PauseGate(), asyncio.Event()

    async def move() -> bool:
        async with gate.interruption() as stretch:
            moving.set()
            await asyncio.sleep(3600)
        return stretch.interrupted

    run = asyncio.create_task(move())
    await moving.wait()
    gate.pause()
    assert run.cancelling() == 1  # requested in pause() itself, not a turn later
    assert await asyncio.wait_for(run, 1) is True


async def test_a_step_that_fails_still_ends() -> None:
    gate = PauseGate()
    try:
        async with gate.step():
            raise RuntimeError("device fault")
    except RuntimeError:
        pass
    gate.pause()
    await asyncio.wait_for(gate.settled(), 1)

"""A run cancelled just as its move to the safe position ends is still cancelled.

Why: asyncio.wait_for on Python 3.11 drops a cancellation that arrives in the loop
turns between the awaited call finishing and wait_for returning (CPython gh-86296).
A move bounded that way would let the run go on after the cell had left its state
(a cancel, or an e-stop's CANCEL_RUN), and the worker would wait
emergency_stop_timeout for a task that never ends; the move is bounded with
asyncio.timeout.
"""

from __future__ import annotations

import asyncio

import pytest

from server.core.operations.base import OperationContext
from server.core.operations.safe_position import move_to_safe_position
from server.drivers.base import Pose
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot


class ArrivingRobot(FakeRobot):
    """A robot whose move ends when the test says so."""

    def __init__(self) -> None:
        super().__init__()
        self.arrive = asyncio.Event()
        self.moving = asyncio.Event()

    async def move_linear(self, pose: Pose, speed: float, acceleration: float) -> None:
        self.moving.set()
        await self.arrive.wait()


@pytest.mark.parametrize("turns", range(8))
async def test_a_cancel_in_any_turn_after_the_move_ends_ends_the_run(turns: int) -> None:
    robot = ArrivingRobot()
    ctx = OperationContext(
        robot=robot,
        glue=FakeGlue(),
        camera=FakeCamera(),
        settings=Settings(),
        stores=None,  # type: ignore[arg-type]  # the move touches no store
        params={},
    )

    async def run() -> None:
        await move_to_safe_position(ctx)
        await asyncio.sleep(3600)  # the rest of the run: only a cancel ends it

    task = asyncio.ensure_future(run())
    await robot.moving.wait()
    robot.arrive.set()
    for _ in range(turns):
        await asyncio.sleep(0)
    task.cancel()
    done, _ = await asyncio.wait({task}, timeout=2)
    assert task in done and task.cancelled()

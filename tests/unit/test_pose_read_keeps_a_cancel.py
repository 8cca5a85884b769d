"""A cancel that lands just as a bounded pose read ends is not lost.

The worker reads the pose before a jog, and the marker teaching reads it before
recording a position. Both were bounded with asyncio.wait_for, which on Python
3.11 drops a cancellation arriving in the loop turns between the read ending
and wait_for returning (CPython gh-86296): a worker cancelled at that moment
would go on to start the jog.
"""

from __future__ import annotations

import asyncio

import pytest

from server.core.operations.jog import read_pose_within
from server.drivers.base import Pose
from tests.fakes import FakeRobot


class AnsweringRobot(FakeRobot):
    """A robot whose position read ends when the test says so."""

    def __init__(self) -> None:
        super().__init__()
        self.answer = asyncio.Event()
        self.asked = asyncio.Event()

    async def get_position(self) -> Pose:
        self.asked.set()
        await self.answer.wait()
        return Pose(400.0, 0.0, 200.0)


@pytest.mark.parametrize("turns", range(8))
async def test_a_cancel_in_any_turn_after_the_read_ends_is_kept(turns: int) -> None:
    robot = AnsweringRobot()

    async def jog() -> None:
        await read_pose_within(robot, 5.0)
        await asyncio.sleep(3600)  # the rest of the worker's turn: only a cancel ends it

    task = asyncio.ensure_future(jog())
    await robot.asked.wait()
    robot.answer.set()
    for _ in range(turns):
        await asyncio.sleep(0)
    task.cancel()
    done, _ = await asyncio.wait({task}, timeout=2)
    assert task in done and task.cancelled(), "the cancel was swallowed"


async def test_a_read_with_no_answer_times_out() -> None:
    robot = AnsweringRobot()
    with pytest.raises(TimeoutError):
        await read_pose_within(robot, 0.05)

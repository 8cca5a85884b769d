"""The robot moves only when a person, or a run a person commanded, needs it to.

Entering IDLE (after start-up, after a run, after a reset following an e-stop) starts
no move: a homing move at travel speed there is one nobody asked for.
"""

from __future__ import annotations

import asyncio

from server.core.machine.transitions import Event, State
from server.drivers.base import Pose
from tests.conftest import START_PAYLOAD, wait_for_state
from tests.fakes import FakeRobot


async def _quiet(seconds: float = 0.1) -> None:
    await asyncio.sleep(seconds)  # long enough for a homing move to have been sent


async def test_coming_up_to_idle_moves_nothing(make_worker) -> None:
    robot = FakeRobot()
    await make_worker(robot=robot)
    await _quiet()
    assert robot.moves == []


async def test_a_reset_after_an_estop_leaves_the_robot_where_it_stopped(make_worker) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    await worker.stops.stop(source="test")
    assert (await worker.request(Event.RESET_REQUESTED, source="test")).accepted
    await _quiet()
    assert worker.ctx.state is State.IDLE and robot.moves == []


async def test_home_sends_the_robot_to_its_safe_position_and_stays_idle(
    make_worker, fast_settings
) -> None:
    robot = FakeRobot()
    worker = await make_worker(robot=robot)
    outcome = await worker.request(Event.HOME_REQUESTED, source="test")
    assert outcome.accepted and outcome.state is State.IDLE
    async with asyncio.timeout(5):
        while not robot.moves:
            await asyncio.sleep(0.005)
    assert robot.moves == [Pose.from_sequence(fast_settings.safe_position)]


async def test_home_is_refused_when_the_safe_position_is_outside_the_workspace(
    make_worker, fast_settings
) -> None:
    """The settings refuse such a position at load; the worker checks it again before it
    moves the robot (a settings object changed after load is not checked again)."""
    robot = FakeRobot()
    outside = (900.0, 0.0, 200.0, 180.0, 0.0, 0.0)  # x beyond workspace_max_mm
    worker = await make_worker(
        fast_settings.model_copy(update={"safe_position": outside}), robot=robot
    )
    outcome = await worker.request(Event.HOME_REQUESTED, source="test")
    assert not outcome.accepted and "outside the workspace (x=900.0 mm" in outcome.message
    await _quiet()
    assert robot.moves == [] and worker.ctx.state is State.IDLE


async def test_a_run_begins_at_the_safe_position_and_its_end_moves_nothing_more(
    make_worker, fast_settings
) -> None:
    robot = FakeRobot(speed_factor=1000)
    worker = await make_worker(robot=robot)
    await worker.request(Event.START_REQUESTED, source="test", payload=START_PAYLOAD)
    await wait_for_state(worker, State.IDLE)
    assert robot.moves[0] == Pose.from_sequence(fast_settings.safe_position)
    moves_at_end = len(robot.moves)
    await _quiet()
    assert len(robot.moves) == moves_at_end  # no homing after the run

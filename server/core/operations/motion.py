"""A move a pause can interrupt: the robot stops where it is, and the run knows where.

Why not just hold between moves: a spray segment lasts up to a second or
more, and a pause that waited for its end would leave the arm moving with the
valve open after PAUSED was reported. So a move inside a pause-gate step is
cancelled by the pause on the spot (the driver sends `stop`; a move that
had not sent `moveL` yet never sends it, so nothing starts after the
worker's stop), the robot is confirmed still and its pose is read; the
operation then closes the valve, leaves the step, holds, and on resume
re-approaches that pose and continues the same segment from there.

The move runs in the run's own task, in a `gate.interruption()`: the pause
cancels the task there, and the block tells that cancellation from any other
(a cancel or a timeout of the run goes on up). No task per move, so a move
that answers at once costs no loop turn.
"""

from __future__ import annotations

import asyncio
import math

from server.common.errors import OperationError
from server.core.operations.base import OperationContext
from server.drivers.base import Pose

ARRIVED_MM = 0.5  # a move stopped this close to its target counts as finished
STILL_POLL_S = 0.005


async def pausable_move(ctx: OperationContext, target: Pose, speed: float) -> Pose | None:
    """Move linearly to `target`: None once there, or the pose where a pause stopped it.

    Call it inside `ctx.gate.step()`. A pause already requested stops the
    robot without starting the move. A move that failed while a pause was
    being made is taken as stopped by the pause (the worker's own stop makes
    the driver report an interrupted move); whether the robot really answers
    is then found by `stop_here`, whose failure fails the run.
    """
    gate = ctx.gate
    if gate.paused:
        return await stop_here(ctx, target)
    interruption = gate.interruption()  # a pause cancels the move here; the driver sends stop
    try:
        async with interruption:
            await ctx.robot.move_linear(target, speed, ctx.settings.acceleration_mm_s2)
    except Exception:
        if not gate.paused:
            raise  # the move failed: the fault is the run's
        # failed while a pause was made: stopped by the worker's own stop, the pause's
    if not gate.paused:
        return None
    return await stop_here(ctx, target)


async def stop_here(ctx: OperationContext, target: Pose) -> Pose | None:
    """Stop the robot, wait until it is still, and say where it is (None: at `target`).

    Bounded by pause_hold_timeout: a robot that does not confirm it is still
    fails the run (PAUSE_NOT_HELD), which sends the cell to ERROR and halts it.
    """
    robot = ctx.robot
    limit = ctx.settings.pause_hold_timeout
    try:
        async with asyncio.timeout(limit):
            await robot.stop()
            while True:  # a real arm decelerates; the stop's answer is not the standstill
                if not await robot.is_moving():
                    break
                await asyncio.sleep(STILL_POLL_S)
            pose = await robot.get_position()
    except TimeoutError:
        raise OperationError(
            "PAUSE_NOT_HELD",
            f"the robot did not confirm it stood still within {limit:g} s of the pause "
            "(pause_hold_timeout)",
        ) from None
    return None if math.dist(pose[:3], target[:3]) <= ARRIVED_MM else pose


def at(pose: Pose, other: Pose) -> bool:
    """Two poses the same point for the purpose of a re-approach."""
    return math.dist(pose[:3], other[:3]) <= ARRIVED_MM

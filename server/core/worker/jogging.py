"""A jog's start: read the pose, check the step's target against the workspace, then move.

The pose is read here, in the worker, because the worker alone starts moves
outside operations: read while no move is under way, it is where the step
starts. The read is bounded by emergency_stop_timeout, so the worker is never
held long; an e-stop or a fault while it was read refuses the jog before
anything moves (`JogRefused`, answered as a refusal: nothing moved).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from server.core.machine.events import JogPayload
from server.core.operations.jog import JogRefused, jog_target, read_pose_within
from server.core.worker.startup import Activities
from server.drivers.base import Robot
from server.settings.model import Settings


async def start_jog(
    payload: JogPayload,
    *,
    robot: Robot,
    activities: Activities,
    settings: Settings,
    stops: Callable[[], tuple[int, int]],
    known_faults: Callable[[], tuple[str, ...]],
) -> None:
    """Start the jog's one bounded step, or raise JogRefused with why nothing moved.

    `stops` counts the e-stops requested and the faults reported so far;
    `known_faults` is what the devices' health reports now.
    """
    if activities.moving:
        raise JogRefused("the robot is still moving (home or a jog): jog once it stands")
    before = stops()
    limit = settings.emergency_stop_timeout
    try:
        pose = await read_pose_within(robot, limit)
    except asyncio.CancelledError:
        raise
    except Exception as exc:
        reason = f"no answer within {limit:g} s" if isinstance(exc, TimeoutError) else exc
        message = f"the robot's position could not be read ({reason}); nothing moved"
        raise JogRefused(message) from None
    target = jog_target(pose, payload.axis, payload.distance_mm, settings)
    if stops() != before or known_faults():
        raise JogRefused("a stop or a fault came in while the jog was decided; nothing moved")
    activities.jog(target)

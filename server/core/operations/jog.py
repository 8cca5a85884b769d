"""A jog: one bounded step of the robot along one axis, for maintenance teaching markers.

Why a step and not a target: a person at the table says "5 mm further in x", and
the server, which alone knows where the arm is, works out where that is. The
step is bounded (jog_max_step_mm) before the worker is asked; the target is
checked against the workspace once the worker has read the pose, before any
motion. Either refusal names the request's field and changes nothing.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

from server.core.operations.safe_position import workspace_problem
from server.drivers.base import Pose, Robot
from server.settings.model import Settings
from server.settings.motion import MotionSettings

AXES = ("x", "y", "z")


@dataclass(frozen=True, slots=True)
class JogRefused(Exception):
    """A jog refused once the pose was known; nothing moved. `field` names a wrong field."""

    message: str
    field: str | None = None

    def __str__(self) -> str:
        return self.message


def step_problem(axis: str, distance_mm: float, settings: MotionSettings) -> tuple[str, str] | None:
    """(field, why) when the step itself is wrong, before anything is read or moved."""
    if axis not in AXES:
        return "axis", f"axis must be one of {', '.join(AXES)}, not {axis!r}"
    if distance_mm == 0:  # a move command to where the arm stands: nothing a person meant
        return "distance_mm", "a jog step of 0 mm moves nothing: give the step in mm"
    limit = settings.jog_max_step_mm
    if not abs(distance_mm) <= limit:
        return "distance_mm", (
            f"a jog step of {distance_mm:g} mm exceeds jog_max_step_mm ({limit:g} mm): "
            "jog in smaller steps"
        )
    return None


def jog_target(pose: Pose, axis: str, distance_mm: float, settings: Settings) -> Pose:
    """Where a step of `distance_mm` along `axis` from `pose` ends; JogRefused outside.

    The orientation is kept: a jog translates the tool, it never turns it.
    """
    index = AXES.index(axis)
    target = pose._replace(**{axis: pose[index] + distance_mm})
    problem = workspace_problem(target, settings)
    if problem is not None:
        raise JogRefused(
            f"the jog's target is outside the workspace ({problem}): from "
            f"{axis}={pose[index]:.1f} mm a step of {distance_mm:g} mm leaves it",
            field="distance_mm",
        )
    return target


async def read_pose_within(robot: Robot, limit: float) -> Pose:
    """The robot's pose, or TimeoutError after `limit` seconds.

    Bounded with asyncio.timeout, not asyncio.wait_for: on Python 3.11 wait_for
    drops a cancellation that arrives in the loop turns between the read ending
    and wait_for returning (CPython gh-86296), and a jog decided after its
    worker was cancelled would move the arm nobody is watching any more.
    """
    async with asyncio.timeout(limit):
        return await robot.get_position()

"""The robot's safe position: where a run begins and where `home` sends it.

Why here and not on entering IDLE: the robot moves only when a person or a
running operation they commanded needs it to. So a reset, a restart or the
end of a run never moves the robot; the move to the safe position is the
first step of the next commanded operation (and the whole of the `home`
command), and its target is checked against the workspace before it moves.
"""

from __future__ import annotations

from server.common.errors import OperationError
from server.core.infra.eager import within
from server.core.operations.base import OperationContext
from server.core.operations.motion import pausable_move
from server.drivers.base import Pose
from server.settings.motion import MotionSettings, outside_workspace


def workspace_problem(pose: Pose, settings: MotionSettings) -> str | None:
    """Which axis of `pose` leaves the workspace (the message), or None when it is inside."""
    return outside_workspace(pose, settings.workspace_min_mm, settings.workspace_max_mm)


def safe_pose(settings: MotionSettings) -> Pose:
    """The safe position, refused with WORKSPACE_VIOLATION when it lies outside the workspace."""
    pose = Pose.from_sequence(settings.safe_position)
    problem = workspace_problem(pose, settings)
    if problem is not None:
        raise OperationError(
            "WORKSPACE_VIOLATION",
            f"the safe position is outside the workspace ({problem}): correct safe_position "
            "or the workspace bounds in the settings",
        )
    return pose


async def move_to_safe_position(ctx: OperationContext) -> None:
    """The first step of a run: travel to the safe position, checked before any motion.

    A pause during the move stops the robot where it is; resume sends it on.
    """
    settings = ctx.settings
    pose = safe_pose(settings)
    while True:
        async with ctx.gate.step():
            try:
                # Not asyncio.wait_for: on Python 3.11 it swallows a cancellation that
                # arrives as the move finishes (CPython gh-86296), so a cancel or an
                # e-stop could leave the run going on after the cell left its state.
                # `within` is asyncio.timeout, set only if the move has to wait.
                move = pausable_move(ctx, pose, settings.travel_speed_mm_s)
                stopped = await within(move, settings.safe_position_timeout)
            except TimeoutError as exc:
                limit = settings.safe_position_timeout
                raise OperationError(
                    "SAFE_POSITION_FAILED",
                    f"the robot did not reach its safe position within {limit:g} s "
                    "(safe_position_timeout)",
                ) from exc
            if stopped is None:
                return

"""The robot's safe position: where a run begins and ends, and where `home` sends it.

Why inside the run and not on entering IDLE: the robot moves only when a person
or a running operation they commanded needs it to. So a reset, a restart or
entering IDLE never moves the robot; the move to the safe position is the first
step of a commanded run, its last step (the specification's exit action of
EXECUTING_TRAJECTORY: the arm leaves the part, so the next one can be loaded;
`retract_after_run`), and the whole of the `home` command. Its target is checked
against the workspace before it moves, and a pause, a cancel or an e-stop stop it
like any move of the run. A run cancelled or failed ends where it stopped.

The retract and the inspection overlap (`retract_and_inspect`): the inspection
waits only until the arm has cleared the camera's view of the part (the tool
`inspection_clearance_mm` outside the beads it laid, in x and y), takes its frame,
and does its vision work while the arm travels on.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from typing import Any, TypeVar

from server.common.errors import OperationError
from server.core.infra.eager import within
from server.core.operations.base import OperationContext
from server.core.operations.motion import pausable_move
from server.drivers.base import Pose
from server.settings.motion import MotionSettings, outside_workspace

log = logging.getLogger(__name__)

T = TypeVar("T")
CLEARANCE_POLL_S = 0.02  # how often the retract's position is read for the camera's view
RETRACT_STEP = "retracting to the safe position"


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


def clear_of(pose: Sequence[float], beads: Sequence[Sequence[float]], clearance: float) -> bool:
    """Whether the tool at `pose` is `clearance` mm outside the box (x, y) of `beads`'
    points: the arm no longer stands between the camera and the part. No beads: clear."""
    if not beads:
        return True
    xs = [point[0] for point in beads]
    ys = [point[1] for point in beads]
    x, y = pose[0], pose[1]
    return (
        x < min(xs) - clearance
        or x > max(xs) + clearance
        or y < min(ys) - clearance
        or y > max(ys) + clearance
    )


async def _watch_clearance(
    ctx: OperationContext, beads: Sequence[Sequence[float]], cleared: asyncio.Event
) -> None:
    """Set `cleared` once the robot's position is clear of the beads (`clear_of`)."""
    clearance = ctx.settings.inspection_clearance_mm
    while not cleared.is_set():
        try:
            pose = await ctx.robot.get_position()
        except Exception as exc:  # the retract's own move reports a lost robot
            log.debug("the retract's position could not be read: %s", exc)
            return
        if clear_of(pose, beads, clearance):
            cleared.set()
            return
        await asyncio.sleep(CLEARANCE_POLL_S)


async def retract_and_inspect(
    ctx: OperationContext,
    beads: Sequence[Sequence[float]],
    inspect: Callable[[Callable[[], Awaitable[object]]], Coroutine[Any, Any, T]] | None,
) -> T | None:
    """The run's last step: the arm to the safe position; with `inspect`, its result.

    `inspect` is called at once with a function to await before it takes its frame:
    that returns once the arm is clear of `beads` (or at the safe position). The move
    runs in the run's own task (a pause interrupts it there: motion.py), the inspection
    beside it; the run ends when both have. Either failing fails the run, and the other
    is stopped first.
    """
    cleared = asyncio.Event()
    watcher = asyncio.create_task(_watch_clearance(ctx, beads, cleared))
    inspection: asyncio.Task[T] | None = None
    if inspect is not None:
        inspection = asyncio.create_task(inspect(cleared.wait))
    try:
        await move_to_safe_position(ctx)
        cleared.set()
        return await inspection if inspection is not None else None
    finally:
        cleared.set()
        tasks = [task for task in (watcher, inspection) if task is not None]
        for task in tasks:
            task.cancel()  # a no-op for one done already
        # Their own outcomes were seen above; a cancellation of this run still goes on up.
        await asyncio.gather(*tasks, return_exceptions=True)

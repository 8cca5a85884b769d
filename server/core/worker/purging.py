"""A purge of the glue line: an activity in IDLE, like home and jog, never a state.

The `purge` command moves the nozzle to purge_position (over the purge cup), then
opens the valve at purge_flow_ml_min for purge_seconds and closes it. It needs no
state of its own: like a jog it is one bounded piece of work a person commanded
in IDLE, run as the worker's one background activity (`Activities`), so leaving
IDLE (a start, a fault, the e-stop) cancels it with CANCEL_HOMING, after the
row's HALT has closed the valve and stopped the robot.

The valve is never opened after a stop or a fault: the counts of e-stops
requested and faults posted are read when the purge is decided and again just
before the valve opens, with no await between that check and the command, so a
stop that came in during the move is never undone. However the purge ends, its
`finally` closes the valve (shielded, so a cancellation still sends the close).
Its glue, valve cycle and robot travel are counted by the drivers; the purge
itself and the new start of the pot life by the care meter.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from server.core.operations.jog import JogRefused
from server.core.operations.safe_position import workspace_problem
from server.core.worker.care import CareMeter
from server.core.worker.startup import Activities
from server.drivers.base import DeviceFault, GlueDispenser, Pose, Robot
from server.settings.model import Settings

log = logging.getLogger(__name__)


def start_purge(
    *,
    robot: Robot,
    glue: GlueDispenser,
    activities: Activities,
    settings: Settings,
    care: CareMeter,
    stops: Callable[[], tuple[int, int]],
    post_fault: Callable[[DeviceFault], None],
) -> None:
    """Start the purge, or raise JogRefused (answered 409, nothing moved) saying why not."""
    if activities.moving:
        raise JogRefused("the robot is still moving (home, a jog or a purge): purge once it stands")
    target = Pose.from_sequence(settings.purge_position)
    problem = workspace_problem(target, settings)
    if problem is not None:
        raise JogRefused(
            f"the purge position is outside the workspace ({problem}): correct "
            "purge_position or the workspace bounds in the settings; nothing moved"
        )
    activities.purge(_purge(robot, glue, target, settings, care, stops, stops(), post_fault))


PURGE_SETTLE_S = 1.5  # from the arm's arrival to the valve's opening


async def _purge(
    robot: Robot,
    glue: GlueDispenser,
    target: Pose,
    settings: Settings,
    care: CareMeter,
    stops: Callable[[], tuple[int, int]],
    before: tuple[int, int],
    post_fault: Callable[[DeviceFault], None],
) -> None:
    opened, stage = False, "robot"
    try:
        await robot.move_linear(target, settings.travel_speed_mm_s, settings.acceleration_mm_s2)
        stage = "glue"
        await glue.set_flow_rate(settings.purge_flow_ml_min)
        # The arm settles over the purge cup before glue flows: a speed-following
        # dispenser gives its fixed flow only to a valve opened with the arm at rest.
        await asyncio.sleep(PURGE_SETTLE_S)
        if stops() != before:
            return  # a stop or a fault since the purge was decided: the valve stays closed
        opened = True
        await glue.set_valve(True)
        await asyncio.sleep(settings.purge_seconds)
    except asyncio.CancelledError:
        raise
    except Exception as exc:
        if stops() == before:  # not the stop's own doing: a fault like any other
            post_fault(DeviceFault(stage, "PURGE_FAILED", f"the purge failed: {exc}"))
    finally:
        if opened:
            try:
                await asyncio.shield(glue.set_valve(False))
            except Exception as exc:  # the halt of the stop or fault closes it too
                log.warning("closing the glue valve after the purge failed: %s", exc)
            finally:
                care.purged()

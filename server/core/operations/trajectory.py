"""Trajectory execution: spray each workpiece's path, waypoint by waypoint.

The whole path is planned first (every workpiece, from its spray settings)
and checked against the workspace before the robot moves at all, so a
violation never leaves a half-sprayed part. During the run the valve is open
only on spraying segments. A pause stops the robot where it is, mid-segment
(`motion.pausable_move`), and the valve is closed before the run holds; resume
re-approaches that point and sprays the rest of the segment. It is closed
whenever the run ends, however it ends.

Planning is bounded and stoppable. It runs on a thread of its own
(`_PLANNER`, one at a time), not on the shared default pool, so a long plan
never queues the library reads and vision calls of other requests behind it.
A thread cannot be cancelled, so the planner is stopped cooperatively: the
path functions call a checkpoint in their loops, which raises once the run
is cancelled (cancel, e-stop, processing_timeout) or planning_timeout has
passed; the run waits for the planning to have stopped before it ends. A plan
that runs out of time fails the run with PLANNING_TIMEOUT before any motion
of the path. At each checkpoint the planner also gives the GIL away, so the
event loop answering other requests does not wait for a switch interval
(5 ms) at every turn while a plan runs.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from server.common.errors import OperationError
from server.core.operations.base import OperationContext, OperationResult, OperationWarning
from server.core.operations.inspection import Inspection, inspect_run
from server.core.operations.motion import at, pausable_move
from server.core.operations.safe_position import (
    RETRACT_STEP,
    retract_and_inspect,
    workspace_problem,
)
from server.core.operations.workpieces import Target, locate_workpieces
from server.drivers.base import Pose
from server.quality.model import spray_segments
from server.quality.sampler import RunSampler
from server.settings.model import Settings
from server.storage.inspection_images import NoRoomForImage
from server.vision.paths import Checkpoint, SprayPattern, spray_polylines

log = logging.getLogger(__name__)

# Why a completed run's part was not inspected, in its result's `not_inspected`.
NOT_INSPECTED_NO_SPACE = "no space"
TRAVEL_CLEARANCE_MM = 50.0
# One planning at a time, off the default pool (see the module's docstring).
_PLANNER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="path-planning")


class PlanningStopped(Exception):
    """Raised inside the planner at its next checkpoint once the planning is to stop."""


def _carry_on() -> None:
    """No stop: the planning runs to its end (direct calls, tests)."""


@dataclass(frozen=True, slots=True)
class Waypoint:
    """A pose to reach, whether glue flows on the way there, and for which workpiece."""

    pose: Pose
    spray: bool
    speed: float
    workpiece: str
    flow_rate_ml_min: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "pose": list(self.pose),
            "spray": self.spray,
            "speed": self.speed,
            "workpiece": self.workpiece,
        }


def plan_path(
    targets: Sequence[Target], settings: Settings, checkpoint: Checkpoint = _carry_on
) -> list[Waypoint]:
    """Travel above each polyline, descend, spray along it, lift; workpiece after workpiece.

    `checkpoint` is called in the planner's loops; what it raises stops the planning.
    """
    z = settings.spray_height_mm
    travel_z = z + TRAVEL_CLEARANCE_MM
    travel = settings.travel_speed_mm_s
    path: list[Waypoint] = []
    for target in targets:
        spray = target.spray
        pattern = SprayPattern(
            outline_offset_mm=spray.outline_offset_mm,
            outline=spray.outline,
            fill=spray.fill,
            fill_spacing_mm=spray.fill_spacing_mm,
            fill_angle_deg=spray.fill_angle_deg,
        )
        try:
            outline = np.asarray(target.outline_mm, dtype=np.float64)
            polylines = spray_polylines(outline, pattern, checkpoint=checkpoint)
        except ValueError as exc:
            raise OperationError("PATH_INVALID", f"workpiece {target.workpiece_id}: {exc}") from exc
        for line in polylines:
            checkpoint()
            (x0, y0), name = line[0], target.workpiece_id
            path.append(Waypoint(Pose(x0, y0, travel_z), False, travel, name))
            path.append(Waypoint(Pose(x0, y0, z), False, travel, name))
            path.extend(
                Waypoint(
                    Pose(float(x), float(y), z),
                    True,
                    spray.speed_mm_s,
                    name,
                    spray.flow_rate_ml_min,
                )
                for x, y in line[1:]
            )
            path.append(
                Waypoint(
                    Pose(float(line[-1][0]), float(line[-1][1]), travel_z), False, travel, name
                )
            )
    if not path:
        raise OperationError("PATH_EMPTY", "the spray settings give nothing to spray")
    return path


async def plan_within_limit(targets: Sequence[Target], settings: Settings) -> list[Waypoint]:
    """`plan_path` on the planner's thread, stopped at planning_timeout or on cancellation.

    Returns only once the planning has stopped, whichever way: a cancelled or
    timed-out plan leaves no work behind. Raises OperationError PLANNING_TIMEOUT
    when the limit is reached.
    """
    stop = threading.Event()

    def checkpoint() -> None:
        if stop.is_set():
            raise PlanningStopped
        time.sleep(0)  # gives the GIL away: the event loop never waits out a switch interval

    loop = asyncio.get_running_loop()
    planning = loop.run_in_executor(_PLANNER, plan_path, targets, settings, checkpoint)
    limit = settings.planning_timeout
    try:
        async with asyncio.timeout(limit):
            return await asyncio.shield(planning)
    except TimeoutError:
        await _stop(planning, stop)
        error = planning.exception()
        if error is None:  # it finished in the same instant: keep the plan
            return planning.result()
        if not isinstance(error, PlanningStopped):
            raise error from None  # its own failure (an invalid path) as it is
        names = ", ".join(t.workpiece_id for t in targets)
        raise OperationError(
            "PLANNING_TIMEOUT",
            f"planning the path of {names} took longer than {limit:g} s (planning_timeout); "
            "nothing has moved along it: coarsen the fill spacing or simplify the outline "
            "(PUT /workpieces/{id}), or raise planning_timeout",
        ) from None
    except asyncio.CancelledError:
        await _stop(planning, stop)
        raise


async def _stop(planning: asyncio.Future[list[Waypoint]], stop: threading.Event) -> None:
    """Stop the planning and wait until it has: at its next checkpoint, within milliseconds."""
    stop.set()
    await asyncio.wait({planning})
    planning.exception()  # retrieved: a stopped plan is not an unhandled error


def check_workspace(path: Sequence[Waypoint], settings: Settings) -> None:
    """Refuse the whole path before any motion if one waypoint leaves the workspace."""
    for index, waypoint in enumerate(path, start=1):
        problem = workspace_problem(waypoint.pose, settings)
        if problem is not None:
            raise OperationError(
                "WORKSPACE_VIOLATION",
                f"waypoint {index} of {len(path)} ({waypoint.workpiece}) is outside the "
                f"workspace: {problem}; move the part inside the workspace or check the "
                "calibration",
            )


async def resolve_targets(ctx: OperationContext) -> list[Target]:
    """The named workpiece as stored, or the library parts found on the table."""
    workpiece_id = ctx.params.get("workpiece_id")
    if ctx.params.get("contour_matching", True):
        return await locate_workpieces(ctx, workpiece_id)
    if not workpiece_id:
        raise OperationError("NO_WORKPIECE", "start without contour matching needs a workpiece_id")
    try:
        entry = await asyncio.to_thread(ctx.stores.workpieces.get, workpiece_id)
    except KeyError as exc:
        raise OperationError(
            "WORKPIECE_UNKNOWN", f"workpiece {workpiece_id!r} is not in the library"
        ) from exc
    return [Target(entry.id, entry.name, np.asarray(entry.outline_mm), entry.spray)]


async def execute_trajectory(ctx: OperationContext) -> OperationResult:
    """Plan, check and spray; report progress after every waypoint."""
    targets = await resolve_targets(ctx)
    path = await plan_within_limit(targets, ctx.settings)
    check_workspace(path, ctx.settings)
    ctx.publish_plan(
        [w.as_dict() for w in path],
        [{"workpiece_id": t.workpiece_id, "name": t.name, "match": t.match} for t in targets],
    )
    glue = ctx.glue
    await glue.set_pressure(ctx.settings.default_pressure_psi)
    valve_open = False
    flow = None
    inspecting = ctx.settings.inspection_enabled
    segments, segment_of = spray_segments(path)
    sampler = RunSampler(ctx.robot, glue, ctx.settings.quality_sample_interval_s)

    async def close_valve() -> None:
        nonlocal valve_open
        if valve_open:
            await glue.set_valve(False)
            valve_open = False
            sampler.closed()

    if inspecting:
        sampler.start()
    try:
        index = 0
        resume_at: Pose | None = None  # where a pause stopped the robot inside path[index]
        while index < len(path):
            waypoint = path[index]
            async with ctx.gate.step(on_hold=close_valve):
                if resume_at is not None:
                    # Back to where the pause stopped the arm, valve closed, then the rest
                    # of the same segment with glue: no gap, nothing sprayed twice.
                    if not at(await ctx.robot.get_position(), resume_at):
                        back = await pausable_move(ctx, resume_at, ctx.settings.travel_speed_mm_s)
                        if back is not None:
                            continue  # paused again on the way back: same point next time
                    resume_at = None
                if waypoint.spray and waypoint.flow_rate_ml_min != flow:
                    flow = waypoint.flow_rate_ml_min
                    await glue.set_flow_rate(flow)
                if waypoint.spray != valve_open and not ctx.gate.paused:
                    # Counted open from the moment the command may be on the line, so a
                    # cancellation in flight still closes it in `finally`.
                    valve_open = valve_open or waypoint.spray
                    await glue.set_valve(waypoint.spray)
                    valve_open = waypoint.spray
                    if valve_open:
                        sampler.opened(segment_of[index])
                    else:
                        sampler.closed()
                sampler.drawing(segment_of.get(index))
                resume_at = await pausable_move(ctx, waypoint.pose, waypoint.speed)
                if ctx.gate.paused:
                    # The valve closed by the run itself too, before the step ends: an open
                    # it had queued may have landed after the worker's close.
                    await close_valve()
                if resume_at is not None:
                    continue  # stopped mid-segment: resume continues it from there
            index += 1
            ctx.report(
                {
                    "waypoint": index,
                    "total": len(path),
                    "fraction": round(index / len(path), 4),
                    "workpiece_id": waypoint.workpiece,
                }
            )
        await close_valve()
    finally:
        # However the run ends (cancel, fault, e-stop), the valve must not stay open.
        if valve_open:
            await asyncio.shield(_close_quietly(ctx))
        samples = await sampler.stop()
    data: dict[str, Any] = {
        "workpieces": [t.workpiece_id for t in targets],
        "waypoints": len(path),
    }

    async def inspect(cleared: Callable[[], Awaitable[object]] | None = None) -> Inspection:
        # The glue is the dispenser's count up to its first poll after the close.
        await sampler.closed_reading(ctx.settings.glue_system_timeout)
        return await inspect_run(ctx, targets, segments, samples, cleared)

    if ctx.settings.retract_after_run:
        # The last step, on record like every step: the arm leaves the part for the safe
        # position; the inspection takes its frame once the arm is out of the way.
        ctx.report(
            {
                "step": RETRACT_STEP,
                "waypoint": len(path),
                "total": len(path),
                "fraction": 1.0,
                "workpiece_id": path[-1].workpiece if path else None,
            }
        )
        beads = [w.pose[:2] for w in path if w.spray]
        found = await retract_and_inspect(ctx, beads, inspect if inspecting else None)
        if not inspecting:
            return OperationResult(data)
        assert found is not None
        inspection = found
    elif not inspecting:
        return OperationResult(data)
    else:
        # No progress message of its own: the last waypoint's (fraction 1.0) stands until
        # the run completes, so every progress message a client sees advances the waypoint.
        inspection = await inspect()
    images = ctx.stores.inspection_images
    if inspection.image_jpeg is not None and images is not None:
        try:
            await asyncio.to_thread(images.save, ctx.run_id, inspection.image_jpeg)
        except NoRoomForImage as exc:
            return not_inspected_for_space(ctx.run_id, data, inspection.summary, exc)
    return OperationResult(
        {**data, "inspection": inspection.summary}, inspection.warnings, inspection.document
    )


def not_inspected_for_space(
    run_id: str, data: dict[str, Any], summary: dict[str, Any], exc: OSError
) -> OperationResult:
    """A sprayed part whose inspection image the full disk could not take.

    The part was sprayed whole: failing the run would count a good part as a failed one
    and stop an order over a disk. Nor is a verdict kept without the image and the
    journal row that back it (on a full disk neither can be relied on): the part is
    recorded as not inspected, "no space" (`not_inspected` in the run's result, the
    order's part reason), and a warning says what the inspection had found, and what
    to do. What it found is kept as `inspection_found` (verdict and reasons), so a
    defect it saw still counts the part defective in its order.
    """
    why = exc.strerror or "no space left"
    found = summary.get("verdict", "nothing")
    log.warning("run %s: the inspection image could not be written (%s)", run_id, why)
    warning = OperationWarning(
        "INSPECTION_NO_SPACE",
        f"run {run_id}'s inspection image could not be written ({why}): the part is "
        f"recorded as not inspected (no space); the inspection had found it {found}. "
        "Free space on the data disk (old inspection images, logs, backups), then check "
        "the part by eye",
    )
    found = {"verdict": summary.get("verdict"), "reasons": list(summary.get("reasons") or ())}
    return OperationResult(
        {**data, "not_inspected": NOT_INSPECTED_NO_SPACE, "inspection_found": found}, (warning,)
    )


async def _close_quietly(ctx: OperationContext) -> None:
    try:
        await ctx.glue.set_valve(False)
    except Exception as exc:  # the worker's safe halt closes it again and records the fault
        log.warning("closing the glue valve after the run failed: %s", exc)

"""Trajectory execution: follow a spray path waypoint by waypoint with the glue valve.

The path is planned first and checked against the workspace before the robot
moves at all, so a violation never leaves a half-sprayed part. During the run
the valve is opened only for segments that spray, and it is closed before the
robot holds for a pause and whenever the run ends, however it ends.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from server.config import Settings
from server.core.operations.base import OperationContext
from server.drivers.base import Pose
from server.errors import OperationError

log = logging.getLogger(__name__)

# A 120 × 80 mm rectangular part centred on the table, used when no workpiece is named.
DEMO_OUTLINE_MM: tuple[tuple[float, float], ...] = (
    (340.0, -40.0),
    (460.0, -40.0),
    (460.0, 40.0),
    (340.0, 40.0),
)


@dataclass(frozen=True, slots=True)
class Waypoint:
    """A pose to reach, and whether glue flows on the way there."""

    pose: Pose
    spray: bool
    speed: float

    def as_dict(self) -> dict[str, Any]:
        return {"pose": list(self.pose), "spray": self.spray, "speed": self.speed}


def plan_outline(outline_mm: Sequence[tuple[float, float]], settings: Settings) -> list[Waypoint]:
    """A closed spray path along `outline_mm` at spray height, with travel in and out."""
    if len(outline_mm) < 3:
        raise OperationError("PATH_INVALID", "an outline needs at least 3 points")
    z = settings.spray_height_mm
    travel_z = z + 50.0
    first = outline_mm[0]
    path = [Waypoint(Pose(first[0], first[1], travel_z), False, settings.travel_speed_mm_s)]
    path.append(Waypoint(Pose(first[0], first[1], z), False, settings.travel_speed_mm_s))
    for x, y in [*outline_mm[1:], first]:
        path.append(Waypoint(Pose(x, y, z), True, settings.spray_speed_mm_s))
    path.append(Waypoint(Pose(first[0], first[1], travel_z), False, settings.travel_speed_mm_s))
    return path


def check_workspace(path: Sequence[Waypoint], settings: Settings) -> None:
    """Refuse the whole path before any motion if one waypoint leaves the workspace."""
    low, high = settings.workspace_min_mm, settings.workspace_max_mm
    for index, waypoint in enumerate(path, start=1):
        for axis, value, lo, hi in zip("xyz", waypoint.pose[:3], low, high, strict=True):
            if not lo <= value <= hi:
                raise OperationError(
                    "WORKSPACE_VIOLATION",
                    f"waypoint {index} of {len(path)} is outside the workspace: "
                    f"{axis}={value:.1f} mm, allowed {lo:.0f}..{hi:.0f} mm; "
                    "check the workpiece position and the calibration",
                )


async def execute_trajectory(ctx: OperationContext) -> dict[str, Any]:
    """Plan, check and spray the path; report progress after every waypoint."""
    outline = ctx.params.get("outline_mm") or DEMO_OUTLINE_MM
    workpiece = ctx.params.get("workpiece_id") or "demo"
    path = plan_outline(outline, ctx.settings)
    check_workspace(path, ctx.settings)
    ctx.report({"planned_path": [w.as_dict() for w in path], "workpiece": workpiece})

    glue = ctx.glue
    await glue.set_flow_rate(
        float(ctx.params.get("flow_rate_ml_min", ctx.settings.default_flow_rate_ml_min))
    )
    await glue.set_pressure(ctx.settings.default_pressure_psi)
    valve_open = False

    async def close_valve() -> None:
        nonlocal valve_open
        if valve_open:
            await glue.set_valve(False)
            valve_open = False

    try:
        for index, waypoint in enumerate(path, start=1):
            await ctx.gate.checkpoint(on_hold=close_valve)
            if waypoint.spray != valve_open:
                await glue.set_valve(waypoint.spray)
                valve_open = waypoint.spray
            await ctx.robot.move_linear(
                waypoint.pose, waypoint.speed, ctx.settings.acceleration_mm_s2
            )
            ctx.report(
                {
                    "waypoint": index,
                    "of": len(path),
                    "fraction": round(index / len(path), 4),
                    "workpiece": workpiece,
                }
            )
        await close_valve()
    finally:
        # However the run ends (cancel, fault, e-stop), the valve must not stay open.
        if valve_open:
            await asyncio.shield(_close_quietly(ctx))
    return {"workpiece": workpiece, "waypoints": len(path)}


async def _close_quietly(ctx: OperationContext) -> None:
    try:
        await ctx.glue.set_valve(False)
    except Exception as exc:  # the worker's safe halt closes it again and records the fault
        log.warning("closing the glue valve after the run failed: %s", exc)

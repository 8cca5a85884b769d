"""Operations that so far only verify the camera delivers a usable frame.

Robot calibration, camera calibration and workpiece creation all start from a
camera frame. Until their vision steps land (server/vision), these operations
capture one frame, check its size, and report it: enough to drive the state
machine through every operational state end to end on the simulated cell.
"""

from __future__ import annotations

import asyncio
from typing import Any

from server.core.operations.base import OperationContext
from server.errors import OperationError

MIN_WIDTH, MIN_HEIGHT = 1920, 1080


async def capture_checked_frame(ctx: OperationContext, purpose: str) -> dict[str, Any]:
    """Capture a frame within vision_processing_timeout and check its resolution."""
    try:
        frame = await asyncio.wait_for(ctx.camera.capture(), ctx.settings.vision_processing_timeout)
    except TimeoutError as exc:
        raise OperationError(
            "VISION_TIMEOUT",
            f"{purpose}: no camera frame within {ctx.settings.vision_processing_timeout:g} s",
        ) from exc
    height, width = frame.shape[:2]
    if width < MIN_WIDTH or height < MIN_HEIGHT:
        raise OperationError(
            "FRAME_TOO_SMALL",
            f"{purpose}: camera delivers {width}×{height}, "
            f"at least {MIN_WIDTH}×{MIN_HEIGHT} needed",
        )
    ctx.report({"step": "frame captured", "fraction": 1.0})
    return {"frame": [width, height], "purpose": purpose}


async def calibrate_robot(ctx: OperationContext) -> dict[str, Any]:
    return await capture_checked_frame(ctx, "robot calibration")


async def calibrate_camera(ctx: OperationContext) -> dict[str, Any]:
    return await capture_checked_frame(ctx, "camera calibration")


async def create_workpiece(ctx: OperationContext) -> dict[str, Any]:
    return await capture_checked_frame(ctx, "workpiece creation")

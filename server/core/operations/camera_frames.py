"""Frames for the vision operations: captured in time, and undistorted when the
camera is calibrated, so every measurement is taken on a true pinhole image.

Each undistorted frame is also kept as the cell's latest frame (`ctx.frames`,
GET /camera/frame), so the HMI shows what the operation measured on. The raw
chessboard views of the camera calibration are not: they are distorted, and
show the board, not the table the path is drawn on."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from server.common.errors import OperationError
from server.core.operations.base import OperationContext
from server.storage.calibration import CalibrationStore
from server.vision.homography import PlaneCalibration
from server.vision.intrinsics import undistort_frame
from server.vision.process import IMAGE_PROCESS

MIN_WIDTH, MIN_HEIGHT = 1920, 1080


async def warmed_up(camera: object) -> None:
    """A camera still drawing its first frame since it connected (the simulated one builds
    its render caches then) is waited for, so the timeout that follows is its frame's own."""
    warming = getattr(camera, "warmed_up", None)
    if warming is not None:
        await warming()


async def draw_ahead(camera: object) -> None:
    """A camera that draws its frames (the simulated one) draws what it sees now, so a
    capture soon after waits only for the frame, not for the drawing; other cameras
    stream and need nothing. Never raises."""
    drawing = getattr(camera, "draw_ahead", None)
    if drawing is not None:
        await drawing()


async def capture(ctx: OperationContext, purpose: str) -> np.ndarray:
    """One frame within vision_processing_timeout, at least 1920×1080."""
    timeout = ctx.settings.vision_processing_timeout
    await warmed_up(ctx.camera)
    try:
        async with asyncio.timeout(timeout):  # not wait_for: see safe_position.py
            frame = await ctx.camera.capture()
    except TimeoutError as exc:
        raise OperationError(
            "VISION_TIMEOUT", f"{purpose}: no camera frame within {timeout:g} s"
        ) from exc
    height, width = frame.shape[:2]
    if width < MIN_WIDTH or height < MIN_HEIGHT:
        raise OperationError(
            "FRAME_TOO_SMALL",
            f"{purpose}: the camera delivers {width}×{height}; "
            f"at least {MIN_WIDTH}×{MIN_HEIGHT} is needed",
        )
    return frame


async def capture_undistorted(ctx: OperationContext, purpose: str) -> np.ndarray:
    """A frame as `capture`, undistorted; kept as the latest frame (read-only from here on)."""
    frame = await capture(ctx, purpose)
    taken_at = time.time()
    intrinsics = ctx.stores.calibration.camera
    undistorted = frame
    if intrinsics is not None:  # in the image process, off the server's interpreter lock
        shape = (frame.shape, frame.dtype)
        undistorted = await IMAGE_PROCESS.call(
            undistort_frame, intrinsics, frame=frame, frame_out=shape
        )
    ctx.frames.keep(
        undistorted, source=ctx.operation or purpose, run_id=ctx.run_id, taken_at=taken_at
    )
    return undistorted


def robot_calibration_problem(store: CalibrationStore, purpose: str) -> OperationError | None:
    """Why the image → robot map cannot be used now, or None when it can.

    Checked before a run is accepted (server/core/machine/decide.py) and again,
    raised, when the operation uses it.
    """
    if store.robot is None:
        return OperationError(
            "NOT_CALIBRATED", f"{purpose} needs the robot calibration: run calibrate-robot first"
        )
    made_with = store.robot_meta.get("camera_calibration_at")
    if made_with != store.camera_meta.get("created_at"):
        return OperationError(
            "CALIBRATION_STALE",
            f"{purpose}: the robot calibration predates the current camera calibration; "
            "run calibrate-robot again",
        )
    return None


def require_robot_calibration(ctx: OperationContext, purpose: str) -> PlaneCalibration:
    """The image → robot map, if there is one that matches the current camera calibration."""
    store = ctx.stores.calibration
    problem = robot_calibration_problem(store, purpose)
    if problem is not None:
        raise problem
    assert store.robot is not None
    return store.robot

"""Robot calibration (ArUco markers 0-8 → image-to-table map) and camera
calibration (chessboard views → intrinsics), each validated and persisted."""

from __future__ import annotations

import asyncio
from functools import cache
from typing import Any

import numpy as np

from server.core.operations.base import OperationContext, OperationResult, OperationWarning
from server.core.operations.camera_frames import capture, capture_undistorted
from server.errors import OperationError
from server.vision.homography import PlaneCalibration, annotate_markers, fit_plane_calibration
from server.vision.intrinsics import calibrate_intrinsics, find_chessboard
from server.vision.markers import MarkerDetection, MarkerDetector, missing_markers

REQUIRED_MARKERS = range(9)
MIN_VIEW_SHIFT_PX = 20.0  # a real operator must move the board between views


@cache
def _detector() -> MarkerDetector:
    return MarkerDetector(fast=False)  # calibration wants the reference, not the fast path


def _calibrate_from_frame(
    frame: np.ndarray, marker_positions: list[tuple[float, float]]
) -> tuple[PlaneCalibration, np.ndarray, dict[int, MarkerDetection]]:
    detections = _detector().detect(frame)
    missing = missing_markers(detections, REQUIRED_MARKERS)
    if missing:
        names = ", ".join(str(m) for m in missing)
        plural = "s" if len(missing) > 1 else ""
        raise OperationError(
            "MARKER_NOT_FOUND",
            f"marker{plural} {names} not found: check lighting and that the "
            f"marker{plural} {'are' if plural else 'is'} uncovered",
            recoverable=True,
        )
    pixels = {i: detections[i].centre for i in REQUIRED_MARKERS}
    robot_mm = {i: marker_positions[i] for i in REQUIRED_MARKERS}
    calibration = fit_plane_calibration(pixels, robot_mm)
    return calibration, annotate_markers(frame, detections, calibration.residuals_mm), detections


DEGRADING_SHARE = 0.5  # of calibration_max_error_mm: accepted, but warned of


async def calibrate_robot(ctx: OperationContext) -> OperationResult:
    """Detect markers 0-8, fit the image → robot-plane map, check it, persist it."""
    frame = await capture_undistorted(ctx, "robot calibration")
    ctx.report({"step": "detecting markers", "fraction": 0.3})
    calibration, image, _ = await asyncio.to_thread(
        _calibrate_from_frame, frame, ctx.settings.marker_positions_mm
    )
    limit = ctx.settings.calibration_max_error_mm
    if calibration.mean_error_mm > limit:
        worst = max(calibration.residuals_mm, key=calibration.residuals_mm.__getitem__)
        raise OperationError(
            "CALIBRATION_INACCURATE",
            f"robot calibration mean error {calibration.mean_error_mm:.2f} mm exceeds "
            f"{limit:g} mm (worst: marker {worst}, {calibration.residuals_mm[worst]:.2f} mm); "
            "check the marker positions in the settings and that the markers lie flat",
        )
    store = ctx.stores.calibration
    meta = {
        "markers": len(REQUIRED_MARKERS),
        "camera_calibration_at": store.camera_meta.get("created_at"),
    }
    await asyncio.to_thread(store.save_robot, calibration, image, meta)
    ctx.report({"step": "saved", "fraction": 1.0})
    result: dict[str, Any] = {
        "mean_error_mm": round(calibration.mean_error_mm, 4),
        "max_error_mm": round(calibration.max_error_mm, 4),
        "undistorted": store.camera is not None,
    }
    warnings: tuple[OperationWarning, ...] = ()
    if calibration.mean_error_mm > DEGRADING_SHARE * limit:
        warnings = (
            OperationWarning(
                "CALIBRATION_DEGRADING",
                f"robot calibration mean error {calibration.mean_error_mm:.2f} mm is "
                f"over {DEGRADING_SHARE:.0%} of its {limit:g} mm limit: check that the markers "
                "lie flat and clean, and the camera mount, before it fails",
            ),
        )
    return OperationResult(result, warnings)


REAL_CAMERA_VIEW_INTERVAL_S = 2.0  # time for a person to tilt and move the board


async def calibrate_camera(ctx: OperationContext) -> OperationResult:
    """Collect distinct chessboard views, solve the intrinsics, persist them.

    A simulated camera is asked to show its chessboard views (the simulated
    operator holding the board); a real one needs a person to move the board.
    """
    settings = ctx.settings
    pattern = (settings.chessboard_cols, settings.chessboard_rows)
    wanted = settings.camera_calibration_views
    present = getattr(ctx.camera, "show_chessboard", None)
    if callable(present):
        present()
    interval = settings.camera_calibration_view_interval_s
    if interval is None:
        interval = 0.0 if callable(present) else REAL_CAMERA_VIEW_INTERVAL_S
    corner_sets: list[np.ndarray] = []
    size = (0, 0)
    try:
        for attempt in range(wanted * 3):
            if len(corner_sets) >= wanted:
                break
            if attempt and interval:
                # A person moves the board between captures; the HMI shows this step.
                ctx.report({"step": "move the chessboard to a new pose", "views": len(corner_sets)})
                await asyncio.sleep(interval)
            frame = await capture(ctx, "camera calibration")
            size = (frame.shape[1], frame.shape[0])
            corners = await asyncio.to_thread(find_chessboard, frame, pattern)
            if corners is None or (
                corner_sets and _shift(corners, corner_sets[-1]) < MIN_VIEW_SHIFT_PX
            ):
                continue
            corner_sets.append(corners)
            ctx.report(
                {
                    "step": "collecting views",
                    "views": len(corner_sets),
                    "of": wanted,
                    "fraction": round(len(corner_sets) / (wanted + 1), 4),
                }
            )
    finally:
        show_table = getattr(ctx.camera, "show_table", None)
        if callable(present) and callable(show_table):
            show_table()
    if len(corner_sets) < wanted:
        raise OperationError(
            "CHESSBOARD_NOT_FOUND",
            f"only {len(corner_sets)} of {wanted} views showed the {pattern[0]}×{pattern[1]} "
            "chessboard: hold it fully in view and tilt it differently for each view",
            recoverable=True,
        )
    intrinsics = await asyncio.to_thread(
        calibrate_intrinsics, corner_sets, pattern, settings.chessboard_square_mm, size
    )
    await asyncio.to_thread(
        ctx.stores.calibration.save_camera,
        intrinsics,
        {"pattern": list(pattern), "square_mm": settings.chessboard_square_mm},
    )
    matrix = np.asarray(intrinsics.camera_matrix)
    return OperationResult(
        {
            "reprojection_error_px": round(float(intrinsics.rms_px), 4),
            "fx": round(float(matrix[0, 0]), 2),
            "fy": round(float(matrix[1, 1]), 2),
            "views": intrinsics.views,
            "note": "the robot calibration must be redone after a camera calibration",
        }
    )


def _shift(corners: np.ndarray, previous: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm(corners.reshape(-1, 2) - previous.reshape(-1, 2), axis=1)))

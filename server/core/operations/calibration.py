"""Robot calibration (ArUco markers 0-8 → image-to-table map) and camera
calibration (chessboard views → intrinsics), each validated and persisted."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np

from server.common.errors import OperationError
from server.core.operations.base import OperationContext, OperationResult, OperationWarning
from server.core.operations.camera_frames import capture, capture_undistorted
from server.quality.vision_check import DEGRADING_SHARE
from server.vision.intrinsics import calibrate_intrinsics, find_chessboard
from server.vision.marker_map import (
    REQUIRED_MARKERS,
    MarkersMissing,
    ScaleNotMeasurable,
    calibrate_from_frame,
)
from server.vision.process import IMAGE_PROCESS

MIN_VIEW_SHIFT_PX = 20.0  # a real operator must move the board between views


async def calibrate_robot(ctx: OperationContext) -> OperationResult:
    """Detect markers 0-8, fit the image → robot-plane map, check it, persist it.

    Checked three ways before it replaces the stored map: its own fit (mean residual), its
    scale against the printed marker side (a layout at the wrong scale fits itself
    perfectly), and each marker predicted by a map fitted without it (a wrong marker
    position hides in the fit's residuals). A refused map leaves the stored one in place.
    """
    settings = ctx.settings
    frame = await capture_undistorted(ctx, "robot calibration")
    ctx.report({"step": "detecting markers", "fraction": 0.3})
    try:
        calibration, image_png, checks = await IMAGE_PROCESS.call(
            calibrate_from_frame, settings.marker_positions_mm, frame=frame
        )
    except MarkersMissing as exc:
        names = ", ".join(str(m) for m in exc.missing)
        plural = "s" if len(exc.missing) > 1 else ""
        raise OperationError(
            "MARKER_NOT_FOUND",
            f"marker{plural} {names} not found: check lighting and that the "
            f"marker{plural} {'are' if plural else 'is'} uncovered",
            recoverable=True,
        ) from None
    except ScaleNotMeasurable:
        raise OperationError(
            "CALIBRATION_SCALE",
            "robot calibration scale not measurable: no marker's border edges were found; "
            "check that the markers are clean and evenly lit",
        ) from None
    limit = settings.calibration_max_error_mm
    if calibration.mean_error_mm > limit:
        worst = max(calibration.residuals_mm, key=calibration.residuals_mm.__getitem__)
        raise OperationError(
            "CALIBRATION_INACCURATE",
            f"robot calibration mean error {calibration.mean_error_mm:.2f} mm exceeds "
            f"{limit:g} mm (worst: marker {worst}, {calibration.residuals_mm[worst]:.2f} mm); "
            "check the marker positions in the settings and that the markers lie flat",
        )
    size = settings.marker_size_mm
    scale_error = checks.scale_error_pct(size)
    scale_limit = settings.calibration_max_scale_error_pct
    if abs(scale_error) > scale_limit:
        raise OperationError(
            "CALIBRATION_SCALE",
            f"robot calibration scale is off by {scale_error:+.2f} % (limit {scale_limit:g} %): "
            f"the markers measure {checks.mean_side_mm:.2f} mm through the map, "
            f"marker_size_mm is {size:g} mm; check marker_positions_mm against the table "
            "(measured at the wrong scale?) and marker_size_mm against the printed markers",
        )
    worst, holdout = checks.worst_holdout
    holdout_limit = settings.calibration_max_holdout_error_mm
    if holdout > holdout_limit:
        raise OperationError(
            "CALIBRATION_HOLDOUT",
            f"robot calibration hold-out error {holdout:.2f} mm exceeds {holdout_limit:g} mm: "
            f"a map fitted without marker {worst} misses it by that much (mean over the "
            f"markers {sum(checks.holdout_mm.values()) / len(checks.holdout_mm):.2f} mm); "
            f"check marker {worst}'s position in marker_positions_mm and that it has not moved",
        )
    store = ctx.stores.calibration
    meta = {
        "markers": len(REQUIRED_MARKERS),
        "camera_calibration_at": store.camera_meta.get("created_at"),
        "scale_error_pct": round(scale_error, 4),
        "holdout_max_error_mm": round(holdout, 4),
    }
    await asyncio.to_thread(store.save_robot, calibration, image_png, meta)
    ctx.report({"step": "saved", "fraction": 1.0})
    result: dict[str, Any] = {
        "mean_error_mm": round(calibration.mean_error_mm, 4),
        "max_error_mm": round(calibration.max_error_mm, 4),
        "scale_error_pct": round(scale_error, 4),
        "holdout_max_error_mm": round(holdout, 4),
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
            corners = await IMAGE_PROCESS.call(find_chessboard, pattern, frame=frame)
            if corners is None or (
                corner_sets and _shift(corners, corner_sets[-1]) < MIN_VIEW_SHIFT_PX
            ):
                continue
            corner_sets.append(corners)
            ctx.report(
                {
                    "step": "collecting views",
                    "views": len(corner_sets),
                    "total": wanted,
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

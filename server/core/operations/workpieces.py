"""Workpiece creation, and finding library workpieces on the table.

Both start from an undistorted frame, find part outlines (marker regions left
out), and turn them into millimetres on the table through the robot
calibration.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from pydantic import ValidationError

from server.common.errors import OperationError
from server.core.operations.base import OperationContext, OperationResult
from server.core.operations.camera_frames import capture_undistorted, require_robot_calibration
from server.storage.workpieces import SpraySettings, WorkpieceIn
from server.vision.part_finding import match_parts, measure_part
from server.vision.process import IMAGE_PROCESS


def _not_found(what: str) -> OperationError:
    return OperationError(
        "WORKPIECE_NOT_FOUND",
        f"{what}: no workpiece found on the table; check that it lies fully inside the "
        "camera view, away from the markers, and contrasts with the table",
        recoverable=True,
    )


async def create_workpiece(ctx: OperationContext) -> OperationResult:
    """Capture the part on the table and store its outline (mm) in the library."""
    homography = require_robot_calibration(ctx, "workpiece creation").homography
    frame = await capture_undistorted(ctx, "workpiece creation")
    ctx.report({"step": "finding the outline", "fraction": 0.3})

    library = ctx.stores.workpieces
    entries = await asyncio.to_thread(library.list)
    outlines = {w.id: np.asarray(w.outline_mm, dtype=np.float64) for w in entries}
    measured = await IMAGE_PROCESS.call(measure_part, homography, outlines, frame=frame)
    if measured is None:
        raise _not_found("workpiece creation")
    outline_mm, thumbnail, similar = measured
    if similar is not None:  # which stored part it is, in words as well as figures
        similar["name"] = next(w.name for w in entries if w.id == similar["workpiece_id"])
    if similar is not None and ctx.params.get("if_new"):
        # Asked to store only a new part: nothing stored, the answer says which it is.
        ctx.report({"step": "matches a stored part", "fraction": 1.0})
        return OperationResult(
            {
                "stored": False,
                "similar": similar,
                "message": f"not stored: the part on the table matches {similar['name']!r} "
                f"({similar['workpiece_id']}, outline within {similar['fit_error_mm']:g} mm "
                "RMS); send it again without if_new to store a copy",
            }
        )
    try:
        entry = WorkpieceIn(
            name=ctx.params.get("name") or ctx.params.get("workpiece_id") or "part from camera",
            outline_mm=[(float(x), float(y)) for x, y in outline_mm],
            spray=ctx.params.get("spray") or {},
        )
    except ValidationError as exc:  # the library's limits on what a path may ask of the planner
        first = exc.errors()[0]
        raise OperationError(
            "PATH_INVALID",
            f"the measured part cannot be stored: {'.'.join(map(str, first['loc']))}: "
            f"{first['msg']}; create it with a coarser fill, or store a simplified outline "
            "with POST /workpieces",
        ) from exc
    problem = await asyncio.to_thread(entry.path_problem)  # as POST /workpieces checks
    if problem is not None:
        raise OperationError(
            "PATH_INVALID", f"the measured part cannot be stored: {problem[0]}: {problem[1]}"
        )
    wanted = ctx.params.get("workpiece_id")
    try:
        stored = await asyncio.to_thread(
            library.create, entry, workpiece_id=wanted, source="camera", thumbnail_png=thumbnail
        )
    except FileExistsError as exc:  # taken since the command was accepted
        raise OperationError(
            "WORKPIECE_EXISTS",
            f"workpiece {wanted!r} was created meanwhile; create-workpiece never replaces a part: "
            f"change it with PUT /workpieces/{wanted}",
        ) from exc
    centroid = outline_mm.mean(axis=0)
    ctx.report({"step": "stored", "fraction": 1.0, "workpiece_id": stored.id})
    return OperationResult(
        {
            "stored": True,
            "similar": similar,  # the stored part its outline matched, if any
            "workpiece_id": stored.id,
            "name": stored.name,
            "points": len(outline_mm),
            "area_mm2": round(float(cv2.contourArea(outline_mm.astype(np.float32))), 1),
            "centre_mm": [round(float(c), 2) for c in centroid],
        }
    )


@dataclass(frozen=True)
class Target:
    """One workpiece to spray, with its outline where it lies now (mm, table frame)."""

    workpiece_id: str
    name: str
    outline_mm: np.ndarray
    spray: SpraySettings
    match: dict[str, Any] | None = None


async def locate_workpieces(ctx: OperationContext, only: str | None) -> list[Target]:
    """Find the parts on the table and match each to the library (or to `only`)."""
    homography = require_robot_calibration(ctx, "contour matching").homography
    entries = await asyncio.to_thread(ctx.stores.workpieces.list)
    if only is not None:
        entries = [w for w in entries if w.id == only]
        if not entries:
            raise OperationError("WORKPIECE_UNKNOWN", f"workpiece {only!r} is not in the library")
    if not entries:
        raise OperationError(
            "LIBRARY_EMPTY", "the workpiece library is empty: create a workpiece first"
        )
    library = {w.id: np.asarray(w.outline_mm, dtype=np.float64) for w in entries}
    by_id = {w.id: w for w in entries}
    frame = await capture_undistorted(ctx, "contour matching")

    found = await IMAGE_PROCESS.call(match_parts, homography, library, frame=frame)
    targets = []
    for workpiece_id, placed, figures in found:
        entry = by_id[workpiece_id]
        targets.append(Target(entry.id, entry.name, placed, entry.spray, figures))
    if not targets:
        raise OperationError(
            "WORKPIECE_NOT_MATCHED",
            "no part on the table matches a library workpiece: check the part, the lighting, "
            "or create it as a workpiece first",
            recoverable=True,
        )
    return targets

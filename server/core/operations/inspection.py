"""The inspection after a spray run's path: measure, look at the part, judge, keep.

Called by the trajectory operation once the path is done (inspection_enabled),
so it is part of the run: a run cancelled or failed before it ends has no
inspection, and the run's result carries the summary (the contract of
docs/quality.md). The frame's vision work runs in the image process
(`server.vision.process`), off the server's interpreter lock.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from server.common.errors import OperationError
from server.core.operations.base import OperationContext, OperationWarning
from server.core.operations.camera_frames import (
    capture_undistorted,
    draw_ahead,
    require_robot_calibration,
)
from server.core.operations.workpieces import Target
from server.quality.dispensing import dispensing_consistency
from server.quality.look import look_at_part
from server.quality.model import PlannedSegment, RunSamples
from server.quality.precision import trajectory_precision
from server.quality.trends import bead_width_percent, glue_volume_percent
from server.quality.verdict import dispensing_reasons, precision_reasons, verdict_of
from server.quality.vision_check import PlacedPart, degrading
from server.vision.bead import (
    BeadTolerances,
)
from server.vision.process import IMAGE_PROCESS


@dataclass(frozen=True)
class Inspection:
    """The whole inspection (the journal's row, GET /runs/{id}/inspection), its summary
    (the run's result), its annotated JPEG, and the warnings it raises."""

    document: dict[str, Any]
    summary: dict[str, Any]
    image_jpeg: bytes | None
    warnings: tuple[OperationWarning, ...]


def summary_of(document: dict[str, Any]) -> dict[str, Any]:
    """The run result's "inspection" (the contract's keys, nothing else)."""
    return {
        "verdict": document["verdict"],
        "reasons": list(document["reasons"]),
        "precision_mean_mm": document["precision"]["mean_mm"],
        "precision_p95_mm": document["precision"]["p95_mm"],
        "dispensing_cv_percent": document["dispensing"]["cv_percent"],
        "glue_ml": document["dispensing"]["glue_ml"],
        "vision_residual_mm": document["vision"]["residual_mean_mm"],
        "bead_width_percent": bead_width_percent(document),
        "glue_volume_percent": glue_volume_percent(document),
        "image": bool(document["image"]),
    }


async def inspect_run(
    ctx: OperationContext,
    targets: list[Target],
    segments: list[PlannedSegment],
    samples: RunSamples,
    cleared: Callable[[], Awaitable[object]] | None = None,
) -> Inspection:
    """Measure the run from its samples, capture and judge the part (module docstring).

    `cleared`: awaited before the frame is taken, until the arm no longer hides the
    part (the run's retract, server/core/operations/safe_position.py); the inspection's
    `took_s` counts from then. What needs no frame (the path's precision, the glue's
    consistency, the library's outlines) is worked out while the arm still moves, so
    only the frame and its analysis follow the clearance.
    """
    settings = ctx.settings
    # The bead is laid: a simulated camera draws the part while the arm clears it.
    ahead = asyncio.ensure_future(draw_ahead(ctx.camera)) if cleared is not None else None
    try:
        precision = trajectory_precision(samples.poses, segments)
        dispensing = dispensing_consistency(
            samples.flows, samples.windows, segments, settings.dispensing_flow_tolerance_percent
        )
        entries = await asyncio.to_thread(ctx.stores.workpieces.list)
        library = {w.id: np.asarray(w.outline_mm, dtype=np.float64) for w in entries}
        if cleared is not None:
            await cleared()
    finally:
        if ahead is not None:
            ahead.cancel()  # a drawing begun goes on in the image process, ahead of the frame
    started = time.monotonic()
    try:
        calibration = require_robot_calibration(ctx, "inspection")
        frame = await capture_undistorted(ctx, "inspection")
    except OperationError as exc:
        # The part is sprayed: the run completes, judged on what was measured, and the
        # part counts as defective because nobody has looked at its bead.
        return _unseen(ctx, precision, dispensing, samples, started, str(exc))
    tolerances = BeadTolerances.from_settings(settings)

    positions = list(settings.marker_positions_mm)
    measured = precision_reasons(precision, settings) + dispensing_reasons(dispensing, settings)
    vision, per_segment, parts, reasons, jpeg = await IMAGE_PROCESS.call(
        look_at_part,
        calibration,
        positions,
        [PlacedPart(t.workpiece_id, t.outline_mm) for t in targets],
        library,
        segments,
        tolerances,
        measured,
        settings.bead_max_offset_mm,
        frame=frame,
    )
    scores = [t.match["score"] for t in targets if t.match is not None]
    vision["match_score"] = max(scores) if scores else None
    vision["parts"] = parts
    by_index = {s["index"]: s for s in precision["segments"]}
    for entry in per_segment:
        seg = by_index.get(entry["index"], {})
        entry["precision_mean_mm"] = seg.get("mean_mm")
        entry["precision_max_mm"] = seg.get("max_mm")
        entry["precision_samples"] = seg.get("samples", 0)
    warnings: tuple[OperationWarning, ...] = ()
    limit = settings.calibration_max_error_mm
    if degrading(vision["residual_mean_mm"], limit):
        warnings = (
            OperationWarning(
                "CALIBRATION_DEGRADING",
                f"the calibration markers on run {ctx.run_id}'s inspection frame lie "
                f"{vision['residual_mean_mm']:.2f} mm (mean) from their positions, over "
                f"half of calibration_max_error_mm ({limit:g} mm): the camera or the table "
                "has moved; check the camera mount and run calibrate-robot",
            ),
        )
    document = _document(
        ctx, reasons, precision, dispensing, vision, per_segment, samples, started, jpeg
    )
    return Inspection(document, summary_of(document), jpeg, warnings)


def _document(
    ctx: OperationContext,
    reasons: list[str],
    precision: dict[str, Any],
    dispensing: dict[str, Any],
    vision: dict[str, Any],
    segments: list[dict[str, Any]],
    samples: RunSamples,
    started: float,
    jpeg: bytes | None,
) -> dict[str, Any]:
    """The inspection as journaled and served (GET /runs/{id}/inspection)."""
    return {
        "run_id": ctx.run_id,
        "verdict": verdict_of(reasons),
        "reasons": reasons,
        "at": time.time(),
        "took_s": round(time.monotonic() - started, 3),
        "precision": {k: v for k, v in precision.items() if k != "segments"},
        "dispensing": dispensing,
        "vision": vision,
        "segments": segments,
        "samples": samples.as_counts(),
        "image": jpeg is not None,
    }


def _unseen(
    ctx: OperationContext,
    precision: dict[str, Any],
    dispensing: dict[str, Any],
    samples: RunSamples,
    started: float,
    why: str,
) -> Inspection:
    """The inspection of a part the camera could not look at."""
    settings = ctx.settings
    reasons = [
        *precision_reasons(precision, settings),
        *dispensing_reasons(dispensing, settings),
        f"the bead was not inspected: {why}",
    ]
    vision = {"markers": 0, "residual_mean_mm": None, "residual_max_mm": None}
    segments = [
        {**s, "precision_mean_mm": s["mean_mm"], "precision_max_mm": s["max_mm"]}
        for s in precision["segments"]
    ]
    document = _document(
        ctx, reasons, precision, dispensing, vision, segments, samples, started, None
    )
    return Inspection(document, summary_of(document), None, ())

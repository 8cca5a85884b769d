"""The image process's part of an inspection: the frame's markers, the parts where they
are now, the bead, the part's reasons and the annotated JPEG.

Apart from the inspection (`server/core/operations/inspection.py`) because it runs
in the image process (`server.vision.process`), which imports the module of each
function it is handed: this one imports vision and the quality's pure functions
only, so the image process of a cell with a real camera holds OpenCV and numpy,
not the server's settings, models and operations (docs/benchmarks.md, Memory).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from server.quality.model import PlannedSegment
from server.quality.verdict import part_reasons
from server.quality.vision_check import PlacedPart, marker_residuals, relocate
from server.vision.bead import (
    BeadSegment,
    BeadTolerances,
    annotate_bead,
    expected_bead_width_mm,
    inspect_bead,
)
from server.vision.homography import PlaneCalibration
from server.vision.outlines import transform_outline

JPEG_QUALITY = 85


def look_at_part(
    frame: np.ndarray,
    calibration: PlaneCalibration,
    marker_positions: list[tuple[float, float]],
    targets: list[PlacedPart],
    library: dict[str, np.ndarray],
    segments: list[PlannedSegment],
    tolerances: BeadTolerances,
    measured: list[str],
    max_offset_mm: float,
) -> tuple[dict[str, Any], list[dict[str, Any]], list[Any], list[str], bytes | None]:
    """The frame's vision work: markers, parts, the bead, the part's reasons and the
    annotated JPEG. Run in the image process (`server.vision.process`), so only the JPEG
    and the findings cross.

    The reasons are the part's whole verdict: `measured` (its path and its glue, judged
    before the frame), its position and its bead; the image is stamped from them, so the
    picture and the record never disagree."""
    vision = marker_residuals(frame, calibration, marker_positions)
    parts = relocate(frame, calibration, targets, library)
    moved = {p.workpiece_id: p.transform for p in parts}
    beads = [
        BeadSegment(
            s.index,
            s.workpiece_id,
            transform_outline(s.path_mm, moved[s.workpiece_id])
            if s.workpiece_id in moved
            else s.path_mm,
            expected_bead_width_mm(s.flow_ml_min, s.speed_mm_s),
        )
        for s in segments
    ]
    findings = inspect_bead(frame, beads, calibration, tolerances)
    found = [p.as_dict() for p in parts]
    reasons = (
        measured
        + part_reasons(found, max_offset_mm)
        + [problem for finding in findings for problem in finding.problems]
    )
    annotated = annotate_bead(frame, beads, findings, calibration, reasons)
    ok, jpeg = cv2.imencode(".jpg", annotated, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    per_segment = []
    for bead, finding in zip(beads, findings, strict=True):
        per_segment.append(
            {**finding.as_dict(), "expected_width_mm": round(bead.expected_width_mm, 3)}
        )
    return vision, per_segment, found, reasons, jpeg.tobytes() if ok else None

"""Vision accuracy on the run's inspection frame, and where the part lies now.

The calibration markers are re-detected on the frame taken after the path and
mapped through the stored robot calibration: each one's distance (mm) from its
surveyed position (marker_positions_mm) is its residual. A camera or table
that drifted shows here, run after run, before it spoils parts; over
DEGRADING_SHARE of calibration_max_error_mm raises the CALIBRATION_DEGRADING
warning, as the calibration itself does.

The part is found again (the same outline matching as before the run): how
far it moved since it was matched is a rigid transform, applied to the
planned path so the bead is judged where it should lie on the part now.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from server.vision.homography import PlaneCalibration
from server.vision.outlines import (
    match_outline,
    outline_to_mm,
    part_outlines_px,
    table_marker_detector,
    transform_outline,
)

DEGRADING_SHARE = 0.5  # of calibration_max_error_mm: accepted, but warned of


class Placed(Protocol):
    """A workpiece where it was matched before the run (a run's target)."""

    @property
    def workpiece_id(self) -> str: ...

    @property
    def outline_mm(self) -> np.ndarray: ...


@dataclass(frozen=True)
class PlacedPart:
    """A `Placed` as it crosses to the image process: the id and the outline alone."""

    workpiece_id: str
    outline_mm: np.ndarray


def marker_residuals(
    frame: np.ndarray, calibration: PlaneCalibration, positions: list[tuple[float, float]]
) -> dict[str, Any]:
    """Residual (mm) per marker re-detected on `frame`: mean, max, markers found."""
    found = table_marker_detector().detect(frame)
    residuals: dict[int, float] = {}
    for marker_id, detection in found.items():
        if 0 <= marker_id < len(positions):
            mapped = calibration.to_robot(detection.centre)[0]
            residuals[marker_id] = float(np.linalg.norm(mapped - np.asarray(positions[marker_id])))
    values = list(residuals.values())
    return {
        "markers": len(values),
        "residual_mean_mm": round(float(np.mean(values)), 3) if values else None,
        "residual_max_mm": round(float(np.max(values)), 3) if values else None,
        "residuals_mm": {str(k): round(v, 3) for k, v in sorted(residuals.items())},
    }


def degrading(residual_mean_mm: float | None, limit_mm: float) -> bool:
    """The residual shows the calibration drifting (as calibrate-robot warns)."""
    return residual_mean_mm is not None and residual_mean_mm > DEGRADING_SHARE * limit_mm


@dataclass(frozen=True)
class PartNow:
    """Where a target lies on the inspection frame, against where it was matched."""

    workpiece_id: str
    found: bool
    transform: np.ndarray  # 2×3: planned (matched) position → now; identity if not found
    moved_mm: float  # how far its outline moved, at most over its points
    score: float | None

    def as_dict(self) -> dict[str, Any]:
        return {
            "workpiece_id": self.workpiece_id,
            "found": self.found,
            "moved_mm": round(self.moved_mm, 3),
            "score": None if self.score is None else round(self.score, 5),
        }


IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def relocate(
    frame: np.ndarray,
    calibration: PlaneCalibration,
    targets: Sequence[Placed],
    library: dict[str, np.ndarray],
) -> list[PartNow]:
    """Each target found again on `frame` (the nearest matching outline to where it was)."""
    detected = [outline_to_mm(c, calibration.homography) for c in part_outlines_px(frame)]
    parts = []
    for target in targets:
        best: PartNow | None = None
        outline = library.get(target.workpiece_id)
        if outline is None:
            parts.append(PartNow(target.workpiece_id, False, IDENTITY, 0.0, None))
            continue
        for candidate in detected:
            match = match_outline(candidate, {target.workpiece_id: outline})
            if match is None:
                continue
            placed = transform_outline(outline, match.transform)
            planned = np.asarray(target.outline_mm, dtype=np.float64)
            if len(placed) != len(planned):
                continue
            rigid, _ = cv2.estimateAffinePartial2D(planned, placed, method=cv2.LMEDS)
            if rigid is None:
                continue
            moved = _largest_gap(planned, transform_outline(planned, rigid))
            now = PartNow(target.workpiece_id, True, rigid, moved, float(match.score))
            if best is None or now.moved_mm < best.moved_mm:
                best = now
        parts.append(best or PartNow(target.workpiece_id, False, IDENTITY, 0.0, None))
    return parts


def _largest_gap(planned: np.ndarray, now: np.ndarray) -> float:
    """How far the part's outline now lies from where it was matched (mm): the largest
    distance of a point of either outline to the other outline.

    Outline to outline, not point to matched point: a part that looks the same turned
    (a disc, a square, a hexagon) may be fitted turned, and that is no move at all.
    """
    a, b = planned.astype(np.float32), now.astype(np.float32)
    return max(
        max(abs(cv2.pointPolygonTest(b, (float(x), float(y)), True)) for x, y in a),
        max(abs(cv2.pointPolygonTest(a, (float(x), float(y)), True)) for x, y in b),
    )

"""The glue bead on a part: found along each planned spray segment, measured, judged.

Pure functions on an undistorted BGR frame and the plan (robot mm), mapped
through the robot calibration. A bead pixel is one of the glue's colour
(`BEAD_HSV_LOW`..`BEAD_HSV_HIGH`: the simulated glue is a saturated amber).
Along each segment, every `STEP_MM` the profile across the path (its normal,
out to the expected width plus the offset tolerance on each side) is
searched for bead pixels: their extent is the width there, their centre's
distance from the path the offset; a station without any is part of a gap.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from server.vision.homography import PlaneCalibration

# The bead's cross-section (mm²) is flow over speed; a bead a third as high as it is
# wide (BEAD_ASPECT) then has width sqrt(cross-section / BEAD_ASPECT).
BEAD_ASPECT = 1.0 / 3.0
STEP_MM = 1.0
BEAD_HSV_LOW = (10, 120, 120)
BEAD_HSV_HIGH = (30, 255, 255)
_GREEN, _RED, _ORANGE = (60, 200, 60), (40, 40, 230), (0, 165, 255)


def expected_bead_width_mm(flow_ml_min: float, speed_mm_s: float) -> float:
    """The bead's width from flow over speed (the same physics the simulator renders)."""
    if speed_mm_s <= 0:
        raise ValueError("speed_mm_s must be positive")
    area_mm2 = flow_ml_min * 1000.0 / 60.0 / speed_mm_s
    return float(np.sqrt(max(area_mm2, 0.0) / BEAD_ASPECT))


@dataclass(frozen=True)
class BeadSegment:
    """One planned spray segment: where the bead should lie and how wide."""

    index: int
    workpiece_id: str
    path_mm: np.ndarray
    expected_width_mm: float


@dataclass(frozen=True)
class BeadTolerances:
    width_tolerance_percent: float
    max_gap_mm: float
    max_offset_mm: float

    @classmethod
    def from_settings(cls, settings: Any) -> BeadTolerances:
        return cls(
            settings.bead_width_tolerance_percent,
            settings.bead_max_gap_mm,
            settings.bead_max_offset_mm,
        )


@dataclass
class SegmentBead:
    index: int
    workpiece_id: str
    length_mm: float
    width_mean_mm: float | None
    width_min_mm: float | None
    width_max_mm: float | None
    gaps_mm: list[tuple[float, float]] = field(default_factory=list)
    longest_gap_mm: float = 0.0
    offset_mean_mm: float | None = None
    offset_max_mm: float | None = None
    problems: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        def r(v: float | None) -> float | None:
            return None if v is None else round(float(v), 3)

        return {
            "index": self.index,
            "workpiece_id": self.workpiece_id,
            "length_mm": r(self.length_mm),
            "width_mean_mm": r(self.width_mean_mm),
            "width_min_mm": r(self.width_min_mm),
            "width_max_mm": r(self.width_max_mm),
            "gaps_mm": [[r(a), r(b)] for a, b in self.gaps_mm],
            "longest_gap_mm": r(self.longest_gap_mm),
            "offset_mean_mm": r(self.offset_mean_mm),
            "offset_max_mm": r(self.offset_max_mm),
            "problems": list(self.problems),
        }


def _stations(path: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every STEP_MM along the path, their distance from its start, their normals."""
    points, along, normals = [], [], []
    travelled = 0.0
    for a, b in itertools.pairwise(path):
        vector = b - a
        length = float(np.linalg.norm(vector))
        if length < 1e-9:
            continue
        unit = vector / length
        for s in np.arange(0.0, length, STEP_MM):
            points.append(a + unit * s)
            along.append(travelled + s)
            normals.append((-unit[1], unit[0]))
        travelled += length
    if len(path):
        points.append(path[-1])
        along.append(travelled)
        normals.append(normals[-1] if normals else (0.0, 1.0))
    return np.asarray(points), np.asarray(along), np.asarray(normals)


def _bead_mask(frame: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
    return cv2.inRange(hsv, np.array(BEAD_HSV_LOW), np.array(BEAD_HSV_HIGH)) > 0


def _gaps(found: np.ndarray, along: np.ndarray) -> list[tuple[float, float]]:
    gaps: list[tuple[float, float]] = []
    start: float | None = None
    for hit, s in zip(found, along, strict=False):
        if not hit and start is None:
            start = float(s)
        elif hit and start is not None:
            gaps.append((start, float(s)))
            start = None
    if start is not None:
        gaps.append((start, float(along[-1])))
    return gaps


def _inspect_one(
    mask: np.ndarray,
    segment: BeadSegment,
    calibration: PlaneCalibration,
    tolerances: BeadTolerances,
) -> SegmentBead:
    path = np.asarray(segment.path_mm, dtype=np.float64).reshape(-1, 2)
    points, along, normals = _stations(path)
    reach = segment.expected_width_mm + tolerances.max_offset_mm * 2
    offsets_across = np.arange(-reach, reach + 1e-9, 0.25)
    widths: list[float] = []
    offsets: list[float] = []
    found = np.zeros(len(points), dtype=bool)
    height, width = mask.shape
    for i, (point, normal) in enumerate(zip(points, normals, strict=False)):
        probe = point[None, :] + offsets_across[:, None] * normal[None, :]
        px = np.rint(calibration.to_pixels(probe)).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
        hits = np.zeros(len(px), dtype=bool)
        hits[inside] = mask[px[inside, 1], px[inside, 0]]
        if not hits.any():
            continue
        found[i] = True
        across = offsets_across[hits]
        widths.append(float(across.max() - across.min() + 0.25))
        offsets.append(abs(float((across.max() + across.min()) / 2)))
    length = float(along[-1]) if len(along) else 0.0
    gaps = _gaps(found, along) if len(along) else []
    longest = max((b - a for a, b in gaps), default=0.0)
    bead = SegmentBead(
        segment.index,
        segment.workpiece_id,
        length,
        float(np.mean(widths)) if widths else None,
        float(np.min(widths)) if widths else None,
        float(np.max(widths)) if widths else None,
        gaps,
        longest,
        float(np.mean(offsets)) if offsets else None,
        float(np.max(offsets)) if offsets else None,
    )
    bead.problems = _problems(bead, segment, tolerances)
    return bead


def _problems(bead: SegmentBead, segment: BeadSegment, tol: BeadTolerances) -> list[str]:
    name = f"segment {segment.index} ({segment.workpiece_id})"
    if bead.width_mean_mm is None:
        return [f"{name}: no bead found along its {bead.length_mm:.1f} mm"]
    problems = []
    expected = segment.expected_width_mm
    low, high = (
        expected * (1 - tol.width_tolerance_percent / 100),
        expected * (1 + tol.width_tolerance_percent / 100),
    )
    if bead.width_mean_mm < low or bead.width_mean_mm > high:
        problems.append(
            f"{name}: bead {bead.width_mean_mm:.1f} mm wide, expected {expected:.1f} mm "
            f"± {tol.width_tolerance_percent:g} %"
        )
    if bead.longest_gap_mm > tol.max_gap_mm:
        problems.append(
            f"{name}: a gap of {bead.longest_gap_mm:.1f} mm without bead "
            f"(at most {tol.max_gap_mm:g} mm)"
        )
    if bead.offset_max_mm is not None and bead.offset_max_mm > tol.max_offset_mm:
        problems.append(
            f"{name}: bead up to {bead.offset_max_mm:.1f} mm off its path "
            f"(at most {tol.max_offset_mm:g} mm)"
        )
    return problems


def inspect_bead(
    frame: np.ndarray,
    segments: Sequence[BeadSegment],
    calibration: PlaneCalibration,
    tolerances: BeadTolerances,
) -> list[SegmentBead]:
    """Each segment's bead as found on `frame` (undistorted BGR), with its problems."""
    mask = _bead_mask(frame)
    return [_inspect_one(mask, s, calibration, tolerances) for s in segments]


def annotate_bead(
    frame: np.ndarray,
    segments: Sequence[BeadSegment],
    findings: Sequence[SegmentBead],
    calibration: PlaneCalibration,
) -> np.ndarray:
    """A copy of `frame` with each planned path (green: good, red: a problem), its gaps
    (orange) and the verdict written."""
    image = frame.copy()
    by_index = {f.index: f for f in findings}
    for segment in segments:
        finding = by_index.get(segment.index)
        colour = _GREEN if finding is not None and not finding.problems else _RED
        px = calibration.to_pixels(segment.path_mm).astype(np.int32)
        cv2.polylines(image, [px.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        if finding is None:
            continue
        points, along, _ = _stations(np.asarray(segment.path_mm, dtype=np.float64))
        for start, end in finding.gaps_mm:
            gap = points[(along >= start) & (along <= end)]
            if len(gap) >= 2:
                gap_px = calibration.to_pixels(gap).astype(np.int32)
                cv2.polylines(image, [gap_px.reshape(-1, 1, 2)], False, _ORANGE, 5, cv2.LINE_AA)
        x, y = px[0]
        cv2.putText(
            image,
            str(segment.index),
            (int(x) + 6, int(y) - 6),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.8,
            colour,
            2,
            cv2.LINE_AA,
        )
    good = all(not f.problems for f in findings)
    text = "bead: GOOD" if good else "bead: DEFECTIVE"
    cv2.putText(
        image,
        text,
        (40, 80),
        cv2.FONT_HERSHEY_SIMPLEX,
        2.0,
        _GREEN if good else _RED,
        4,
        cv2.LINE_AA,
    )
    return image

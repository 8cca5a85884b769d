"""The image process's part of the robot calibration: markers 0-8 found in a frame, the
image → table map fitted to them, and the checks independent of its own fit.

Apart from the operation (`server/core/operations/calibration.py`, which words the
refusals and judges the figures against the settings) because it runs in the image
process (`server.vision.process`), which imports the module of each function it is
handed: vision alone, so that process holds OpenCV and numpy, not the server's
settings, models and operations.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from server.vision.homography import (
    PlaneCalibration,
    annotate_markers,
    fit_plane_calibration,
    leave_one_out_errors,
    mapped_side_mm,
)
from server.vision.markers import MarkerDetection, MarkerDetector, border_corners, missing_markers

REQUIRED_MARKERS = range(9)


class MarkersMissing(Exception):
    """Markers of REQUIRED_MARKERS not found in the frame (`missing`, in order)."""

    def __init__(self, missing: list[int]) -> None:
        super().__init__(missing)
        self.missing = missing


class ScaleNotMeasurable(Exception):
    """No marker's border edges were found, so the map's scale cannot be checked."""


@cache
def _detector() -> MarkerDetector:
    return MarkerDetector(fast=False)  # calibration wants the reference, not the fast path


@dataclass(frozen=True)
class IndependentChecks:
    """What the calibration is checked against besides its own fit.

    `side_mm` is each marker's side through the map (its scale against the printed size);
    `holdout_mm` each marker's leave-one-out error (where the map has no marker).
    """

    side_mm: dict[int, float]
    holdout_mm: dict[int, float]

    @property
    def mean_side_mm(self) -> float:
        return sum(self.side_mm.values()) / len(self.side_mm)

    def scale_error_pct(self, marker_size_mm: float) -> float:
        """How far the map's scale is from the printed markers', in %, signed."""
        return 100.0 * (self.mean_side_mm / marker_size_mm - 1.0)

    @property
    def worst_holdout(self) -> tuple[int, float]:
        marker = max(self.holdout_mm, key=self.holdout_mm.__getitem__)
        return marker, self.holdout_mm[marker]


def check_independently(
    frame: np.ndarray,
    calibration: PlaneCalibration,
    detections: dict[int, MarkerDetection],
    marker_positions: list[tuple[float, float]],
) -> IndependentChecks:
    """The markers' sides through the map, and the leave-one-out errors."""
    cells = _detector().dictionary.markerSize + 2  # the black border is one cell wide
    side_mm = {}
    for i in REQUIRED_MARKERS:
        try:
            edges = border_corners(frame, detections[i].corners, cells)
        except ValueError:
            continue  # a smudged border: the other markers still measure the scale
        side_mm[i] = mapped_side_mm(calibration.homography, edges)
    if not side_mm:
        raise ScaleNotMeasurable("no marker's border edges were found")
    holdout_mm = leave_one_out_errors(
        {i: detections[i].centre for i in REQUIRED_MARKERS},
        {i: marker_positions[i] for i in REQUIRED_MARKERS},
    )
    return IndependentChecks(side_mm, holdout_mm)


def calibrate_from_frame(
    frame: np.ndarray, marker_positions: list[tuple[float, float]]
) -> tuple[PlaneCalibration, bytes | None, IndependentChecks]:
    """The map, the annotated frame as PNG, and the checks; run in the image process
    (`server.vision.process`), so only the PNG crosses back, not the frame.
    MarkersMissing or ScaleNotMeasurable when the frame cannot give them."""
    detections = _detector().detect(frame)
    missing = missing_markers(detections, REQUIRED_MARKERS)
    if missing:
        raise MarkersMissing(list(missing))
    pixels = {i: detections[i].centre for i in REQUIRED_MARKERS}
    robot_mm = {i: marker_positions[i] for i in REQUIRED_MARKERS}
    calibration = fit_plane_calibration(pixels, robot_mm)
    checks = check_independently(frame, calibration, detections, marker_positions)
    annotated = annotate_markers(frame, detections, calibration.residuals_mm)
    ok, png = cv2.imencode(".png", annotated)
    return calibration, png.tobytes() if ok else None, checks

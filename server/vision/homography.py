"""The image → table map: a homography from undistorted pixels to robot millimetres on z = 0.

The table is a plane, so once lens distortion is removed (see `server.vision.intrinsics`) a
single 3×3 homography maps every pixel to the robot's (x, y) on the table exactly — tilt and
roll of the camera included. It is fitted by least squares to the nine marker centres: all
of them are trusted (a missing or misread marker is an error before this point), and a robust
method would only throw information away.

Residuals are reported per marker in mm so the operator sees *which* marker disagrees (a
bumped marker shows up as one large residual, a wrong distortion model as a pattern).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.vision.markers import MarkerDetection

__all__ = [
    "PlaneCalibration",
    "annotate_markers",
    "fit_plane_calibration",
    "leave_one_out_errors",
    "mapped_side_mm",
    "pixels_to_robot",
    "robot_to_pixels",
]

MIN_MARKERS = 4  # a homography has 8 degrees of freedom: four points, two equations each

# Residual colours on the annotated image (BGR): good, suspicious, bad.
_GOOD_MM, _WARN_MM = 0.5, 1.0
_GREEN, _ORANGE, _RED = (60, 200, 60), (0, 165, 255), (40, 40, 230)


@dataclass
class PlaneCalibration:
    """Undistorted image pixels → robot mm on the table, with how well the markers fit."""

    homography: np.ndarray  # 3×3, image px → robot mm (table plane)
    residuals_mm: dict[int, float] = field(default_factory=dict)
    mean_error_mm: float = 0.0
    max_error_mm: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-able: lists and floats (marker ids become string keys, as JSON needs)."""
        return {
            "homography": [[float(v) for v in row] for row in np.asarray(self.homography)],
            "residuals_mm": {str(k): float(v) for k, v in self.residuals_mm.items()},
            "mean_error_mm": float(self.mean_error_mm),
            "max_error_mm": float(self.max_error_mm),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PlaneCalibration:
        """Inverse of `to_dict` (also accepts int keys in residuals_mm)."""
        homography = np.asarray(d["homography"], dtype=np.float64)
        if homography.shape != (3, 3):
            raise ValueError(f"homography must be 3×3, got shape {homography.shape}")
        residuals = {int(k): float(v) for k, v in dict(d.get("residuals_mm", {})).items()}
        return cls(
            homography=homography,
            residuals_mm=residuals,
            mean_error_mm=float(d.get("mean_error_mm", 0.0)),
            max_error_mm=float(d.get("max_error_mm", 0.0)),
        )

    def to_robot(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Convenience: `pixels_to_robot(self.homography, pixels)`."""
        return pixels_to_robot(self.homography, pixels)

    def to_pixels(self, points_mm: ArrayLike) -> NDArray[np.float64]:
        """Convenience: `robot_to_pixels(self.homography, points_mm)`."""
        return robot_to_pixels(self.homography, points_mm)


def _as_points(points: ArrayLike) -> NDArray[np.float64]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 1 and pts.size == 2:
        return pts.reshape(1, 2)
    return pts.reshape(-1, 2)


def _apply(matrix: np.ndarray, points: ArrayLike) -> NDArray[np.float64]:
    """Projective map of N×2 points in float64 (cv2.perspectiveTransform keeps the precision)."""
    pts = _as_points(points)
    if len(pts) == 0:
        return np.empty((0, 2))
    out = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), np.asarray(matrix, dtype=np.float64))
    return cast(NDArray[np.float64], out.reshape(-1, 2))


def pixels_to_robot(homography: np.ndarray, pixels: ArrayLike) -> NDArray[np.float64]:
    """Undistorted image points (N×2 px) → robot (x, y) on the table (N×2 mm)."""
    return _apply(homography, pixels)


def robot_to_pixels(homography: np.ndarray, points_mm: ArrayLike) -> NDArray[np.float64]:
    """Robot (x, y) on the table (N×2 mm) → undistorted image points (N×2 px)."""
    return _apply(np.linalg.inv(np.asarray(homography, dtype=np.float64)), points_mm)


def fit_plane_calibration(
    pixels: Mapping[int, ArrayLike], robot_mm: Mapping[int, tuple[float, float]]
) -> PlaneCalibration:
    """Least-squares homography from marker centres (undistorted px) to their robot positions.

    Uses the markers present in both maps; raises ValueError with the ids involved when fewer
    than four are shared or when the markers are degenerate (e.g. all on one line).
    """
    ids = sorted(set(pixels) & set(robot_mm))
    if len(ids) < MIN_MARKERS:
        raise ValueError(
            f"a table calibration needs at least {MIN_MARKERS} markers with both a pixel and a "
            f"robot position; got {len(ids)} (ids {ids})"
        )
    src = np.array([_as_points(pixels[i])[0] for i in ids], dtype=np.float64)
    dst = np.array([tuple(robot_mm[i]) for i in ids], dtype=np.float64)
    homography, _mask = cv2.findHomography(src, dst, 0)
    if homography is None or not np.all(np.isfinite(homography)):
        raise ValueError(f"markers {ids} do not determine a homography (are they on one line?)")
    mapped = pixels_to_robot(homography, src)
    errors = np.linalg.norm(mapped - dst, axis=1)
    return PlaneCalibration(
        homography=homography,
        residuals_mm={i: float(e) for i, e in zip(ids, errors, strict=True)},
        mean_error_mm=float(errors.mean()),
        max_error_mm=float(errors.max()),
    )


def leave_one_out_errors(
    pixels: Mapping[int, ArrayLike], robot_mm: Mapping[int, tuple[float, float]]
) -> dict[int, float]:
    """For each marker, how far (mm) a map fitted to all the *other* markers puts it.

    Why: a fit's own residuals flatter it. With nine markers and eight degrees of freedom a
    marker whose configured position is wrong by 2 mm pulls the map towards itself and shows
    a residual well under 1 mm; predicted from the other eight, it is off by the full 2 mm.
    The hold-out error is the error the map makes where it has no marker (where parts lie).
    Raises ValueError, like `fit_plane_calibration`, when leaving a marker out leaves the
    others degenerate.
    """
    ids = sorted(set(pixels) & set(robot_mm))
    errors: dict[int, float] = {}
    for held in ids:
        rest = [i for i in ids if i != held]
        fit = fit_plane_calibration({i: pixels[i] for i in rest}, {i: robot_mm[i] for i in rest})
        predicted = pixels_to_robot(fit.homography, _as_points(pixels[held])[0])[0]
        errors[held] = float(np.linalg.norm(predicted - np.asarray(robot_mm[held])))
    return errors


def mapped_side_mm(homography: np.ndarray, corners: ArrayLike) -> float:
    """The mean side (mm) of a marker whose corners (4×2 undistorted px) go through the map.

    Why: the printed marker's side is a length known independently of the marker layout, so
    comparing it with what the map makes of it checks the map's scale (a layout measured or
    printed at the wrong scale fits itself perfectly, and only this shows it).
    """
    quad = pixels_to_robot(homography, corners).reshape(4, 2)
    return float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))


def annotate_markers(
    image: np.ndarray,
    detections: Mapping[int, MarkerDetection],
    residuals_mm: Mapping[int, float] | None = None,
) -> np.ndarray:
    """A BGR copy of the frame showing what the calibration saw, for the operator.

    Each marker gets its outline, a cross at its centre, its id and, when given, its residual
    in mm, coloured green (< 0.5 mm), orange (< 1 mm) or red, so a bad marker stands out.
    """
    if image.ndim == 2:
        out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        out = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    else:
        out = image.copy()
    scale = max(out.shape[:2]) / 1920.0
    thickness = max(1, round(2 * scale))
    font_scale = 0.6 * scale
    for marker_id, det in sorted(detections.items()):
        residual = None if residuals_mm is None else residuals_mm.get(marker_id)
        if residual is None:
            colour = _GREEN
        else:
            colour = _GREEN if residual < _GOOD_MM else _ORANGE if residual < _WARN_MM else _RED
        corners = np.asarray(det.corners, dtype=np.float64).reshape(4, 2)
        cv2.polylines(
            out, [np.round(corners).astype(np.int32)], True, colour, thickness, cv2.LINE_AA
        )
        cx, cy = (round(float(v)) for v in det.centre)
        cv2.drawMarker(out, (cx, cy), colour, cv2.MARKER_CROSS, round(12 * scale), thickness)
        side = float(np.linalg.norm(corners[1] - corners[0]))
        label = f"{marker_id}" if residual is None else f"{marker_id}: {residual:.2f} mm"
        origin = (int(corners[:, 0].min()), int(corners[:, 1].min() - 0.2 * side))
        cv2.putText(
            out,
            label,
            origin,
            cv2.FONT_HERSHEY_SIMPLEX,
            font_scale,
            (0, 0, 0),
            thickness + 2,
            cv2.LINE_AA,
        )
        cv2.putText(
            out, label, origin, cv2.FONT_HERSHEY_SIMPLEX, font_scale, colour, thickness, cv2.LINE_AA
        )
    return out

"""Camera intrinsics: chessboard corners, calibration, and undistortion of frames and points.

The table calibration (`server.vision.homography`) is a homography, which only holds on a
pinhole image: with the cell lens's barrel distortion a straight table edge bows by a few
pixels towards the image corners, a few millimetres on the table. So frames (or measured
points) are undistorted first, *keeping the same camera matrix*: the undistorted image has
the same pixel scale and principal point as the raw one, and pixels stay comparable.

Chessboard detection runs on a half-resolution copy (OpenCV's detector is slow on 1080p
frames and needs no more than ~25 px per square) and the corners are refined at full
resolution with `cv2.cornerSubPix`, which is as accurate as searching at full resolution.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.vision.markers import to_gray

__all__ = [
    "MIN_VIEWS",
    "Intrinsics",
    "Undistorter",
    "calibrate_intrinsics",
    "chessboard_object_points",
    "find_chessboard",
    "intrinsics_of",
]

MIN_VIEWS = 5  # below this calibrateCamera is poorly conditioned for 5 distortion terms
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 0.001)
_POINT_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
_FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
_SEARCH_MAX_WIDTH = 1000  # px: frames wider than this are searched at a reduced size


@dataclass
class Intrinsics:
    """A calibrated camera: K, distortion (OpenCV's order), image size and fit quality."""

    camera_matrix: np.ndarray  # 3×3
    dist_coeffs: np.ndarray  # (k1, k2, p1, p2, k3[, ...])
    image_size: tuple[int, int]  # (w, h)
    rms_px: float = 0.0  # reprojection error of the calibration
    views: int = 0  # number of chessboard views it was computed from

    def to_dict(self) -> dict[str, Any]:
        """JSON-able: lists, floats and ints."""
        return {
            "camera_matrix": [[float(v) for v in row] for row in np.asarray(self.camera_matrix)],
            "dist_coeffs": [float(v) for v in np.ravel(self.dist_coeffs)],
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
            "rms_px": float(self.rms_px),
            "views": int(self.views),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Intrinsics:
        """Inverse of `to_dict`."""
        matrix = np.asarray(d["camera_matrix"], dtype=np.float64)
        if matrix.shape != (3, 3):
            raise ValueError(f"camera_matrix must be 3×3, got shape {matrix.shape}")
        width, height = (int(v) for v in d["image_size"])
        return cls(
            camera_matrix=matrix,
            dist_coeffs=np.asarray(d["dist_coeffs"], dtype=np.float64).ravel(),
            image_size=(width, height),
            rms_px=float(d.get("rms_px", 0.0)),
            views=int(d.get("views", 0)),
        )

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])


def chessboard_object_points(pattern: tuple[int, int], square_mm: float) -> NDArray[np.float32]:
    """Inner corners in the board's frame (N×3 mm), row by row as OpenCV reports them."""
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * float(square_mm)
    return np.hstack([grid, np.zeros((len(grid), 1))]).astype(np.float32)


def find_chessboard(
    image: np.ndarray, pattern: tuple[int, int], *, refine: bool = True
) -> NDArray[np.float64] | None:
    """Inner corners (cols·rows × 2 px, OpenCV's order) of a chessboard, or None if not seen.

    Searched on a copy at most ~1000 px wide, then refined at full resolution in windows of
    about a third of a square, so each window holds one corner's four squares and no other
    corner.
    """
    gray = to_gray(image)
    factor = 1
    while gray.shape[1] / factor > _SEARCH_MAX_WIDTH:
        factor *= 2
    small = gray
    if factor > 1:
        size = (gray.shape[1] // factor, gray.shape[0] // factor)
        small = cast(NDArray[np.uint8], cv2.resize(gray, size, interpolation=cv2.INTER_AREA))
    found, corners = cv2.findChessboardCorners(small, tuple(pattern), flags=_FIND_FLAGS)
    if not found or corners is None:
        return None
    # pixel centre c of the small image covers full-resolution pixels factor·c … factor·c+f-1
    pts = corners.reshape(-1, 2).astype(np.float64) * factor + (factor - 1) / 2.0
    if not refine:
        return pts
    cols, rows = pattern
    grid = pts.reshape(rows, cols, 2)
    spacing = [
        np.linalg.norm(np.diff(grid, axis=a), axis=2).min() for a in (0, 1) if grid.shape[a] > 1
    ]
    square_px = float(min(spacing)) if spacing else 20.0
    half = int(np.clip(round(0.35 * square_px), 3, 15))
    refined = cv2.cornerSubPix(
        gray, pts.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), _SUBPIX_CRITERIA
    )
    return refined.reshape(-1, 2).astype(np.float64)


def calibrate_intrinsics(
    corner_sets: Sequence[np.ndarray],
    pattern: tuple[int, int],
    square_mm: float,
    image_size: tuple[int, int],
) -> Intrinsics:
    """Camera matrix and distortion (k1, k2, p1, p2, k3) from chessboard views.

    `corner_sets` are `find_chessboard` results of different board poses; `image_size` is
    (w, h). Raises ValueError when fewer than five views are given or a view has the wrong
    number of corners.
    """
    cols, rows = pattern
    if len(corner_sets) < MIN_VIEWS:
        raise ValueError(
            f"intrinsic calibration needs at least {MIN_VIEWS} chessboard views at different "
            f"poses, got {len(corner_sets)}: capture more views, tilting the board each time"
        )
    expected = cols * rows
    image_points = []
    for index, corners in enumerate(corner_sets):
        pts = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
        if len(pts) != expected:
            raise ValueError(
                f"view {index} has {len(pts)} corners; a {cols}×{rows} pattern has {expected}"
            )
        image_points.append(pts.reshape(-1, 1, 2))
    objects = chessboard_object_points(pattern, square_mm)
    object_points = [objects] * len(image_points)
    width, height = (int(v) for v in image_size)
    rms, matrix, dist, _rvecs, _tvecs = cv2.calibrateCamera(
        object_points, image_points, (width, height), None, None
    )
    return Intrinsics(
        camera_matrix=np.asarray(matrix, dtype=np.float64),
        dist_coeffs=np.asarray(dist, dtype=np.float64).ravel(),
        image_size=(width, height),
        rms_px=float(rms),
        views=len(image_points),
    )


class Undistorter:
    """Removes lens distortion from frames and points, keeping the camera matrix (pixel scale).

    The remap tables are computed once (≈ 0.1 s) and reused for every frame. Points are
    undistorted exactly (iterated to 1e-12), frames through fixed-point maps (1/32 px), so
    measuring on an undistorted frame or undistorting raw measurements agree to ~0.05 px.
    """

    def __init__(self, intrinsics: Intrinsics) -> None:
        self.intrinsics = intrinsics
        self.camera_matrix = np.asarray(intrinsics.camera_matrix, dtype=np.float64)
        self.dist_coeffs = np.asarray(intrinsics.dist_coeffs, dtype=np.float64).ravel()
        width, height = (int(v) for v in intrinsics.image_size)
        self.size = (width, height)
        self._map1, self._map2 = cv2.initUndistortRectifyMap(
            self.camera_matrix,
            self.dist_coeffs,
            None,
            self.camera_matrix,
            self.size,
            cv2.CV_16SC2,
        )

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The undistorted frame, same size and camera matrix as the raw one."""
        height, width = image.shape[:2]
        if (width, height) != self.size:
            raise ValueError(
                f"frame is {width}×{height} but the camera was calibrated at "
                f"{self.size[0]}×{self.size[1]}: recalibrate the camera"
            )
        return cv2.remap(
            image, self._map1, self._map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )

    def points(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Raw image points (N×2 px) → where they are in the undistorted frame (N×2 px)."""
        pts = np.asarray(pixels, dtype=np.float64)
        shape = pts.shape
        flat = pts.reshape(-1, 1, 2)
        if len(flat) == 0:
            return pts.astype(np.float64)
        out = cv2.undistortPoints(
            flat,
            self.camera_matrix,
            self.dist_coeffs,
            P=self.camera_matrix,
            criteria=_POINT_CRITERIA,
        )
        return cast(NDArray[np.float64], out.reshape(shape))

    def distort_points(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Undistorted points (N×2 px) → where they appear in the raw frame (the inverse)."""
        pts = np.asarray(pixels, dtype=np.float64)
        shape = pts.shape
        flat = pts.reshape(-1, 2)
        k_inv = np.linalg.inv(self.camera_matrix)
        homog = np.hstack([flat, np.ones((len(flat), 1))]) @ k_inv.T
        rays = np.hstack([homog[:, :2], np.ones((len(flat), 1))])
        out, _ = cv2.projectPoints(
            rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.camera_matrix, self.dist_coeffs
        )
        return cast(NDArray[np.float64], out.reshape(shape))


def intrinsics_of(
    camera_matrix: ArrayLike, dist_coeffs: ArrayLike, size: tuple[int, int]
) -> Intrinsics:
    """Intrinsics from known values (e.g. a data sheet or a simulator's exact model)."""
    return Intrinsics(
        np.asarray(camera_matrix, dtype=np.float64),
        np.asarray(dist_coeffs, dtype=np.float64).ravel(),
        (int(size[0]), int(size[1])),
    )


_undistorters: dict[str, Undistorter] = {}  # in the image process: the latest calibrations'


def undistort_frame(frame: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The frame through `Undistorter(intrinsics)`, its maps built once per calibration.

    Why a function with its own cache: the image process (`server.vision.process`) runs
    it, and there the maps (tens of MB) are built once, not sent with every frame.
    """
    key = json.dumps(intrinsics.to_dict(), sort_keys=True)
    undistorter = _undistorters.get(key)
    if undistorter is None:
        if len(_undistorters) >= 2:  # a recalibration: the old maps are not asked for again
            _undistorters.pop(next(iter(_undistorters)))
        undistorter = _undistorters[key] = Undistorter(intrinsics)
    return undistorter(frame)

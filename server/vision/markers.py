"""ArUco marker detection with sub-pixel corners: the input of the robot calibration.

The robot calibration maps marker centres to known robot positions, so every tenth of a pixel
in a centre is about 0.06 mm on the table. OpenCV's detector alone returns corners from a
polygon approximation of the marker's contour (off by up to a pixel), so both detectors here
refine each corner at full resolution with `cv2.cornerSubPix` and take the centre as the
intersection of the diagonals: perspective keeps the centre on both diagonals, and the small
bias `cornerSubPix` has at a blurred square corner points along the diagonal, so it cancels.

Two ways to find the markers, one refinement:

- reference (`fast=False`): the straightforward detector on the full-resolution frame;
- fast (`fast=True`, the default): the detector on a half-resolution copy (a quarter of the
  pixels, the markers are still ~23 px wide), corners scaled back and refined at full
  resolution in the same small windows. Same refinement, so the centres agree with the
  reference to a few hundredths of a pixel at a fraction of the cost.

Where the fast path's time goes (docs/benchmarks.md): OpenCV's default thresholds the image
three times (adaptive windows 3, 13 and 23 px) and identifies every square-ish contour it
finds, the data cells of large markers included. So the fast path first tries one window
(`_FAST_WINDOW_PX` at half resolution, about three cells of a 45 px marker and one of a
150 px marker, both of which it finds) and, once it has seen the markers, ignores candidates
far smaller than them and searches large markers at quarter resolution. Only when that pass
finds fewer markers than it should (an expected id, or one it saw in the previous frame)
does it pay for OpenCV's three windows, then for the full resolution: a hard frame (glare,
a shadow across a marker, markers suddenly much smaller) costs time, not a marker.

Pure functions on arrays: no I/O, no logging of frames.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "MarkerDetection",
    "MarkerDetector",
    "border_corners",
    "diagonal_intersection",
    "missing_markers",
    "to_gray",
]

# cornerSubPix stops when a step is below this (px) or after this many iterations: tight, so
# two starting points (coarse and full-resolution) converge to the same corner.
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 0.001)
# Frames at least this tall are searched at half resolution in fast mode.
_DOWNSCALE_MIN_HEIGHT = 720
# The one adaptive-threshold window (px, odd) of the fast first pass, at half resolution.
# Measured on the simulator: 11 finds every marker from 45 px (4 px cells at half
# resolution) to 150 px (12 px cells) wide; OpenCV's three windows cost four to six times more.
_FAST_WINDOW_PX = 11
# A marker this wide (px) at the search's resolution is found as reliably as at full
# resolution (the default table's 45 px markers are 22 px at half resolution).
_MIN_SEARCH_SIDE_PX = 22
# Once markers were seen, candidates with a perimeter under this fraction of the smallest
# one seen are skipped before identification (a 150 px marker's data cells are ~1/6 of it).
_MIN_PERIMETER_OF_SEEN = 0.5


@dataclass(frozen=True)
class MarkerDetection:
    """One marker in the image: its id, corners (4×2 px, OpenCV order) and centre (px)."""

    marker_id: int
    corners: np.ndarray  # 4×2 float64 px: top-left, top-right, bottom-right, bottom-left
    centre: np.ndarray  # (2,) px, intersection of the diagonals


def to_gray(image: np.ndarray) -> NDArray[np.uint8]:
    """A single-channel view of a BGR, BGRA or already grey frame."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[..., 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cast(NDArray[np.uint8], cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    if image.ndim == 3 and image.shape[2] == 4:
        return cast(NDArray[np.uint8], cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY))
    raise ValueError(f"expected a grey, BGR or BGRA image, got shape {image.shape}")


def diagonal_intersection(corners: np.ndarray) -> NDArray[np.float64]:
    """Where the diagonals (0-2 and 1-3) of a quadrilateral cross; the mean if they do not."""
    p0, p1, p2, p3 = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    d1, d2 = p2 - p0, p3 - p1
    denom = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(denom) < 1e-12:
        mean: NDArray[np.float64] = np.mean([p0, p1, p2, p3], axis=0)
        return mean
    r = p1 - p0
    t = (r[0] * d2[1] - r[1] * d2[0]) / denom
    crossing: NDArray[np.float64] = p0 + t * d1
    return crossing


def border_corners(image: np.ndarray, corners: np.ndarray, cells: int = 6) -> NDArray[np.float64]:
    """A marker's outer corners (4×2 px, same order) as crossings of its four fitted edges.

    Why not the refined corners: `cornerSubPix` at an L-shaped corner (a dark square on white
    paper, blurred by the lens) settles about a quarter of a pixel inside the square, along the
    diagonal. That cancels for the centre but shortens every side by about 0.5 % on the cell's
    markers, half of what the robot calibration's scale check allows. A blurred straight edge
    has no such bias: its half-way grey level lies on the edge. So each edge is sampled across
    (half a cell into the black border, half a cell out onto the paper) at points along its
    middle, away from the corners; the crossings are fitted with a line, and neighbouring lines
    are intersected. `corners` are the detector's (any accuracy within a pixel or so); `cells`
    is the marker's width in cells, border included (6 for DICT_4X4).
    """
    quad = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
    half = 0.5 * side / cells
    # Only the marker's neighbourhood is converted and sampled (a whole frame is ~2 M pixels).
    height, width = image.shape[:2]
    x0, y0 = (max(int(v) - int(half) - 4, 0) for v in quad.min(axis=0))
    x1 = min(int(quad[:, 0].max()) + int(half) + 6, width)
    y1 = min(int(quad[:, 1].max()) + int(half) + 6, height)
    gray = to_gray(image[y0:y1, x0:x1]).astype(np.float32)
    quad = quad - (x0, y0)
    centre = quad.mean(axis=0)
    across = np.linspace(-half, half, 2 * max(4, round(4 * half)) + 1)
    along = np.linspace(0.15, 0.85, 15)
    end = max(2, len(across) // 5)  # samples averaged for the dark and the light level
    lines: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        unit = (b - a) / np.linalg.norm(b - a)
        normal = np.array([unit[1], -unit[0]])
        if normal @ ((a + b) / 2.0 - centre) < 0:
            normal = -normal  # pointing out of the marker, onto the paper
        base = a + along[:, None] * (b - a)
        samples = base[:, None, :] + across[None, :, None] * normal
        profiles = cv2.remap(
            gray,
            samples[..., 0].astype(np.float32),
            samples[..., 1].astype(np.float32),
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.float64)
        points = []
        for profile, origin in zip(profiles, base, strict=True):
            level = (profile[:end].mean() + profile[-end:].mean()) / 2.0
            above = np.nonzero(profile >= level)[0]
            if len(above) == 0 or above[0] == 0:
                continue  # no dark-to-light step here (a smudge, a shadow): skip the sample
            j = int(above[0])
            fraction = (level - profile[j - 1]) / (profile[j] - profile[j - 1])
            offset = across[j - 1] + fraction * (across[j] - across[j - 1])
            points.append(origin + offset * normal)
        if len(points) < 2:
            u, v = float(centre[0]) + x0, float(centre[1]) + y0
            raise ValueError(f"edge {k} of the marker at ({u:.1f}, {v:.1f}) px not found")
        pts = np.asarray(points)
        mean = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - mean)
        lines.append((mean, vt[0]))
    out = np.empty((4, 2))
    for k in range(4):  # corner k joins edge k-1 (into it) and edge k (out of it)
        (p1, d1), (p2, d2) = lines[k - 1], lines[k]
        t = np.linalg.solve(np.column_stack([d1, -d2]), p2 - p1)
        out[k] = p1 + t[0] * d1 + (x0, y0)
    return out


def missing_markers(found: Iterable[int], required: Iterable[int] = range(9)) -> list[int]:
    """The required marker ids that were not found, sorted (a dict of detections works too)."""
    have = {int(i) for i in found}
    return sorted({int(i) for i in required} - have)


class MarkerDetector:
    """Finds ArUco markers and refines their corners to sub-pixel accuracy.

    Thread-safe: one detector can serve several worker threads (calls are serialised on the
    underlying OpenCV detectors, which is cheap next to the frame capture). In fast mode it
    remembers which markers the last frame showed and how large they were, to decide how
    hard to look: the corners agree whichever pass found them (the same refinement), but a
    marker the quick pass misses is looked for again only if it was seen in the frame before
    or is named in `expected`; pass `expected` where every marker must be looked for.
    """

    def __init__(
        self,
        dictionary_id: int = cv2.aruco.DICT_4X4_50,
        *,
        fast: bool = True,
        max_refine_window_px: int = 6,
    ) -> None:
        self.dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id)
        self.fast = fast
        self.max_refine_window_px = int(max_refine_window_px)
        # No refinement inside OpenCV: ours runs at full resolution in both modes.
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, params)
        self._cells = self.dictionary.markerSize + 2 * params.markerBorderBits
        self._lock = threading.Lock()
        self._quick_params = cv2.aruco.DetectorParameters()
        self._quick_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._quick_params.adaptiveThreshWinSizeMin = _FAST_WINDOW_PX
        self._quick_params.adaptiveThreshWinSizeMax = _FAST_WINDOW_PX
        self._quick = cv2.aruco.ArucoDetector(self.dictionary, self._quick_params)
        self._seen_ids: frozenset[int] = frozenset()
        self._seen_perimeter_px = 0.0  # smallest marker perimeter last seen, half-res px

    def detect(
        self, image: np.ndarray, *, expected: Iterable[int] | None = None
    ) -> dict[int, MarkerDetection]:
        """Markers in a BGR or grey frame, by id, with sub-pixel corners and centres.

        In fast mode a marker missed at half resolution is looked for again at full
        resolution when `expected` names it (or when nothing at all was found), so a
        difficult frame costs time rather than a marker. A marker id seen twice keeps the
        larger one (the smaller is usually a look-alike in the background).
        """
        gray = to_gray(image)
        if self.fast and gray.shape[0] >= _DOWNSCALE_MIN_HEIGHT:
            height, width = gray.shape
            small = cv2.resize(gray, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
            wanted = set() if expected is None else {int(i) for i in expected}
            found = self._find_quick(small)
            if not found or (wanted | self._seen_ids) - found.keys():
                found = {**self._find(small), **found}
            self._remember(found)
            coarse = {i: 2.0 * c + 0.5 for i, c in found.items()}  # small → full px
            if not coarse or wanted - coarse.keys():
                coarse = {**self._find(gray), **coarse}
        else:
            coarse = self._find(gray)
        return {i: self._refine(gray, i, corners) for i, corners in sorted(coarse.items())}

    # --- internals -----------------------------------------------------------------------

    def _find_quick(self, small: np.ndarray) -> dict[int, NDArray[np.float64]]:
        """The fast first pass on the half-resolution frame, corners in its pixels.

        One threshold window; candidates far smaller than the markers last seen skipped
        (OpenCV's perimeter bound is a fraction of the image's larger side). When the markers
        last seen were large enough to stay `_MIN_SEARCH_SIDE_PX` wide at quarter resolution,
        the search runs there (a quarter of the pixels again; the full-resolution refinement
        converges from the coarser corners all the same).
        """
        seen = self._seen_perimeter_px
        quarter = seen / 4.0 >= 2 * _MIN_SEARCH_SIDE_PX
        image = small
        if quarter:
            height, width = small.shape[:2]
            image = cv2.resize(small, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
            seen /= 2.0
        with self._lock:
            rate = _MIN_PERIMETER_OF_SEEN * seen / max(image.shape[:2])
            self._quick_params.minMarkerPerimeterRate = max(0.03, rate)
            self._quick.setDetectorParameters(self._quick_params)
            corners, ids, _rejected = self._quick.detectMarkers(image)
        found = _by_id(corners, ids)
        return {i: 2.0 * c + 0.5 for i, c in found.items()} if quarter else found

    def _remember(self, found: dict[int, NDArray[np.float64]]) -> None:
        """Which markers this frame showed and the smallest one's perimeter, for the next."""
        perimeters = [_perimeter(q) for q in found.values()]
        with self._lock:
            self._seen_ids = frozenset(found)
            self._seen_perimeter_px = min(perimeters, default=0.0)

    def _find(self, gray: np.ndarray) -> dict[int, NDArray[np.float64]]:
        """Raw (pixel-accurate) corners by id with OpenCV's default thresholds."""
        with self._lock:
            corners, ids, _rejected = self._detector.detectMarkers(gray)
        return _by_id(corners, ids)

    def _refine(self, gray: np.ndarray, marker_id: int, corners: np.ndarray) -> MarkerDetection:
        """Sub-pixel corners in a window that stays inside the marker's black border cell.

        The window's half-size is about 0.6 of a marker cell, so it sees the corner's two
        edges and nothing of the data cells or the next corner.
        """
        side = float(np.mean(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
        half = int(np.clip(round(0.6 * side / self._cells), 2, self.max_refine_window_px))
        pts = corners.astype(np.float32).reshape(-1, 1, 2)
        refined = cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        out = refined.reshape(4, 2).astype(np.float64)
        # a corner that wandered off (a bad coarse guess) keeps its coarse position
        drift = np.linalg.norm(out - corners, axis=1)
        out[drift > 2.0 * half] = corners[drift > 2.0 * half]
        out.setflags(write=False)
        centre = diagonal_intersection(out)
        centre.setflags(write=False)
        return MarkerDetection(marker_id, out, centre)


def _by_id(corners: Sequence[np.ndarray], ids: np.ndarray | None) -> dict[int, NDArray[np.float64]]:
    """detectMarkers' answer by id; an id seen twice keeps the larger marker."""
    found: dict[int, NDArray[np.float64]] = {}
    if ids is None:
        return found
    for marker_id, quad in zip(ids.ravel(), corners, strict=True):
        pts = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        key = int(marker_id)
        if key not in found or _area(pts) > _area(found[key]):
            found[key] = pts
    return found


def _perimeter(quad: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))


def _area(quad: np.ndarray) -> float:
    return abs(float(cv2.contourArea(quad.astype(np.float32))))

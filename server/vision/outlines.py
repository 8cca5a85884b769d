"""Workpiece outlines: found in the image, measured in mm, and matched against the library.

Parts are bright (bead-blasted aluminium, grey ~190) on a dark table (~65), so a global
threshold separates them; the threshold only decides *which* pixels belong to a part. Where
the edge is, is measured afterwards, to a few hundredths of a pixel: every contour point is
moved along the outline's normal to where the grey level crosses the midpoint between the
part and the table right there (vignetting and uneven light change both levels across the
frame, the midpoint between them stays on the edge). That makes outlines straight where the
part is straight, so they simplify to few vertices, and centroids and angles accurate far
beyond the 1 mm / 1° the cell needs (a camera pixel is ~0.65 mm on the table).

Matching a detected outline to the library is shape first, pose second: the rigid transform
(rotation + translation, never a mirror) is fitted by point-to-line ICP from several starting
angles, because symmetric parts (a rectangle looks the same turned by 180°) have several
equally good answers; of those, the one closest to the taught orientation is returned, so the
robot's spray path does not start on the far side of the part for no reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.vision.homography import pixels_to_robot
from server.vision.markers import MarkerDetector, to_gray

__all__ = [
    "OutlineMatch",
    "Pose2D",
    "find_outlines",
    "match_outline",
    "outline_pose",
    "outline_to_mm",
    "polygon_area_centroid",
    "resample_closed",
    "transform_outline",
]

Array = NDArray[np.float64]

MIN_CONTRAST = 40.0  # grey levels between table and parts below which nothing is found
_PROFILE_HALF_PX = 3.0  # how far along the normal the sub-pixel search looks, each side
_PROFILE_STEP_PX = 0.25
_TANGENT_SPAN = 3  # contour points each side used for the local tangent


# --- finding outlines in the image ------------------------------------------------------------


def find_outlines(
    image: np.ndarray,
    *,
    min_area_px: float = 2000.0,
    exclude: list[np.ndarray] | None = None,
    threshold: float | None = None,
    subpixel: bool = True,
) -> list[Array]:
    """Outlines (N×2 float px, in image order) of bright parts on the table, largest first.

    `exclude` are polygons (px) whose pixels are ignored: the marker sheets, grown beyond
    the black square to cover the white quiet zone. Regions touching the image border are
    dropped (part of the part is out of view, so its outline would be wrong). `threshold`
    defaults to Otsu's; nothing is found when the two classes differ by less than
    MIN_CONTRAST grey levels (an empty table has no bright class).
    """
    gray = to_gray(image)
    height, width = gray.shape
    smooth = cv2.GaussianBlur(gray, (5, 5), 0)
    if threshold is None:
        level, _ = cv2.threshold(smooth, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        if _class_contrast(smooth, level) < MIN_CONTRAST:
            return []
    else:
        level = float(threshold)
    _, mask = cv2.threshold(smooth, level, 1, cv2.THRESH_BINARY)
    for polygon in exclude or []:
        pts = np.round(np.asarray(polygon, dtype=np.float64).reshape(-1, 2) * 16).astype(np.int32)
        cv2.fillPoly(mask, [pts], 0, cv2.LINE_8, shift=4)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    kept = []
    for contour in contours:
        area = cv2.contourArea(contour)
        if area < min_area_px:
            continue
        x, y, w, h = cv2.boundingRect(contour)
        if x <= 0 or y <= 0 or x + w >= width or y + h >= height:
            continue
        kept.append((area, (x, y, w, h), contour.reshape(-1, 2).astype(np.float64)))
    kept.sort(key=lambda item: -item[0])
    if not subpixel:
        return [c for _, _, c in kept]
    refined = []
    margin = math.ceil(_PROFILE_HALF_PX) + 2
    for _, (x, y, w, h), contour in kept:
        x0, y0 = max(x - margin, 0), max(y - margin, 0)
        x1, y1 = min(x + w + margin, width), min(y + h + margin, height)
        patch = gray[y0:y1, x0:x1].astype(np.float32)
        origin = np.array([x0, y0], dtype=np.float64)
        refined.append(_refine_edge(patch, contour - origin, float(level)) + origin)
    return refined


MARKER_EXCLUSION_SCALE = 1.8  # the printed paper around a marker, with margin


@cache
def table_marker_detector() -> MarkerDetector:
    """The fast marker detector that finding parts and re-checking markers share.

    One instance, because in fast mode it remembers the markers the last frame showed
    (`MarkerDetector`), and the frames of the table are those frames."""
    return MarkerDetector(fast=True)


def part_outlines_px(frame: np.ndarray) -> list[Array]:
    """Part outlines in the frame, largest first, marker regions excluded."""
    exclude = []
    for detection in table_marker_detector().detect(frame).values():
        centre = detection.centre
        exclude.append(centre + (detection.corners - centre) * MARKER_EXCLUSION_SCALE)
    return find_outlines(frame, exclude=exclude)


def _class_contrast(gray: np.ndarray, level: float) -> float:
    """Mean grey of the pixels above `level` minus that of those below (0 if one is empty)."""
    hist = cv2.calcHist([gray], [0], None, [256], [0, 256]).ravel().astype(np.float64)
    grey = np.arange(256, dtype=np.float64)
    split = int(level) + 1
    low, high = hist[:split], hist[split:]
    if low.sum() == 0 or high.sum() == 0:
        return 0.0
    return float((high * grey[split:]).sum() / high.sum() - (low * grey[:split]).sum() / low.sum())


def _refine_edge(gray: NDArray[np.float32], contour: Array, level: float) -> Array:
    """Move each contour point along the local normal onto the edge (midpoint crossing)."""
    n = len(contour)
    if n < 2 * _TANGENT_SPAN + 1:
        return contour
    tangent = np.roll(contour, -_TANGENT_SPAN, axis=0) - np.roll(contour, _TANGENT_SPAN, axis=0)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    norm[norm == 0] = 1.0
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1) / norm
    steps = np.arange(-_PROFILE_HALF_PX, _PROFILE_HALF_PX + 1e-9, _PROFILE_STEP_PX)
    where = contour[:, None, :] + steps[None, :, None] * normal[:, None, :]
    profile = cv2.remap(
        gray,
        where[..., 0].astype(np.float32),
        where[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    profile = profile.astype(np.float64)
    # the local midpoint between the two sides, if the profile spans the edge; else global
    ends = 3
    side_a, side_b = profile[:, :ends].mean(axis=1), profile[:, -ends:].mean(axis=1)
    local = 0.5 * (side_a + side_b)
    spans = np.abs(side_a - side_b) > MIN_CONTRAST
    mid = np.where(spans, local, level)[:, None]
    diff = profile - mid
    sign_change = (diff[:, :-1] > 0) != (diff[:, 1:] > 0)
    centre = len(steps) // 2
    # prefer the crossing nearest to the contour point: weight by distance from the centre
    distance = np.abs(np.arange(len(steps) - 1) + 0.5 - centre)
    cost = np.where(sign_change, distance[None, :], np.inf)
    best = np.argmin(cost, axis=1)
    found = np.isfinite(cost[np.arange(n), best])
    d0 = diff[np.arange(n), best]
    d1 = diff[np.arange(n), best + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(d0 != d1, d0 / (d0 - d1), 0.5)
    offset = steps[best] + np.clip(frac, 0.0, 1.0) * _PROFILE_STEP_PX
    offset = np.where(found & (np.abs(offset) < _PROFILE_HALF_PX - 0.5), offset, 0.0)
    refined: Array = contour + offset[:, None] * normal
    return refined


# --- outlines in millimetres -----------------------------------------------------------------


def polygon_area_centroid(points: ArrayLike) -> tuple[float, Array]:
    """Signed area (positive counter-clockwise) and area centroid of a simple polygon."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    origin = pts.mean(axis=0)  # shoelace on centred points: no cancellation far from 0
    x, y = (pts - origin).T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2.0
    if abs(area) < 1e-12:
        return 0.0, origin
    centroid = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
    return float(area), centroid + origin


def outline_to_mm(
    contour_px: np.ndarray, homography: np.ndarray, *, tolerance_mm: float = 0.3
) -> Array:
    """An image outline (undistorted px) as a table polygon: N×2 mm, counter-clockwise, open.

    Mapped point by point through the homography, then simplified (Douglas-Peucker) so that
    no point of the dense outline is further than `tolerance_mm` from the polygon.
    """
    mm = pixels_to_robot(homography, np.asarray(contour_px, dtype=np.float64).reshape(-1, 2))
    if len(mm) >= 3 and tolerance_mm > 0:
        simplified = cv2.approxPolyDP(mm.astype(np.float32).reshape(-1, 1, 2), tolerance_mm, True)
        # keep float64 vertices: snap each simplified vertex back to its original point
        chosen = simplified.reshape(-1, 2).astype(np.float64)
        mm = _nearest_points(mm, chosen)
    keep = np.linalg.norm(mm - np.roll(mm, 1, axis=0), axis=1) > 1e-9
    mm = mm[keep] if keep.any() else mm[:1]
    if len(mm) >= 3 and polygon_area_centroid(mm)[0] < 0:
        mm = mm[::-1]
    return np.ascontiguousarray(mm)


def _nearest_points(dense: Array, chosen: Array) -> Array:
    """For each chosen (float32-rounded) vertex, the dense point it came from."""
    index = np.argmin(((dense[None, :, :] - chosen[:, None, :]) ** 2).sum(axis=2), axis=1)
    nearest: Array = dense[index]
    return nearest


@dataclass(frozen=True)
class Pose2D:
    """Where a part lies: area centroid (mm) and principal-axis angle (° CCW from +x)."""

    x: float
    y: float
    theta_deg: float


def _second_moments(outline: Array, centre: Array) -> tuple[float, float, float]:
    """∫x², ∫y², ∫xy over the polygon's area, about `centre` (signs follow the orientation)."""
    x, y = (np.asarray(outline, dtype=np.float64) - centre).T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    ixx = (cross * (x * x + x * xn + xn * xn)).sum() / 12.0
    iyy = (cross * (y * y + y * yn + yn * yn)).sum() / 12.0
    ixy = (cross * (x * yn + 2 * x * y + 2 * xn * yn + xn * y)).sum() / 24.0
    return float(ixx), float(iyy), float(ixy)


def outline_pose(outline_mm: np.ndarray) -> Pose2D:
    """Area centroid and principal-axis angle in (-90°, 90°] of a polygon in mm.

    The angle is that of the long axis (the axis of least inertia). It is meaningless for
    parts whose inertia is the same in every direction (a square, a disc, a regular
    hexagon); use `match_outline` for those.
    """
    pts = np.asarray(outline_mm, dtype=np.float64).reshape(-1, 2)
    area, centroid = polygon_area_centroid(pts)
    ixx, iyy, ixy = _second_moments(pts, centroid)
    if area < 0:
        ixx, iyy, ixy = -ixx, -iyy, -ixy
    theta = 0.5 * math.degrees(math.atan2(2.0 * ixy, ixx - iyy))
    if theta <= -90.0:
        theta += 180.0
    return Pose2D(float(centroid[0]), float(centroid[1]), float(theta))


def transform_outline(outline_mm: np.ndarray, transform: np.ndarray) -> Array:
    """Apply a 2×3 (rigid or affine) transform to N×2 points."""
    pts = np.asarray(outline_mm, dtype=np.float64).reshape(-1, 2)
    matrix = np.asarray(transform, dtype=np.float64).reshape(2, 3)
    return pts @ matrix[:, :2].T + matrix[:, 2]


def resample_closed(outline: ArrayLike, count: int) -> Array:
    """`count` points evenly spaced along a closed polygon's perimeter (first vertex first)."""
    pts = np.asarray(outline, dtype=np.float64).reshape(-1, 2)
    closed = np.vstack([pts, pts[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return np.repeat(pts[:1], count, axis=0)
    at = np.arange(count) * cum[-1] / count
    index = np.clip(np.searchsorted(cum, at, side="right") - 1, 0, len(seg) - 1)
    t = (at - cum[index]) / np.where(seg[index] > 0, seg[index], 1.0)
    resampled: Array = closed[index] + t[:, None] * (closed[index + 1] - closed[index])
    return resampled


# --- matching against the library -------------------------------------------------------------


@dataclass(frozen=True)
class OutlineMatch:
    """The library part a detected outline is, and how it moved since it was taught.

    `transform` (2×3) maps the library outline onto the detected one: a turn by
    `rotation_deg` (CCW) about the library outline's area centroid, then a shift of that
    centroid by `translation_mm`. `score` is dimensionless, 0 for a perfect match: the RMS
    distance between the aligned outlines over the square root of the library part's area,
    plus |ln(area ratio)| (so a larger copy of a shape does not match). `fit_error_mm` is
    that RMS distance.
    """

    workpiece_id: str
    score: float
    rotation_deg: float
    translation_mm: tuple[float, float]
    transform: np.ndarray
    fit_error_mm: float


def match_outline(
    detected_mm: np.ndarray,
    library: dict[str, np.ndarray],
    *,
    max_score: float = 0.1,
) -> OutlineMatch | None:
    """The best-matching library outline and its rigid transform, or None above `max_score`.

    Of symmetric solutions that fit equally well (within 5 % or 0.02 mm), the smallest turn
    is returned; for a disc that is ~0°.
    """
    detected = np.asarray(detected_mm, dtype=np.float64).reshape(-1, 2)
    if len(detected) < 3:
        return None
    area_det = abs(polygon_area_centroid(detected)[0])
    if area_det <= 0:
        return None
    candidates = []
    for workpiece_id, outline in library.items():
        lib = np.asarray(outline, dtype=np.float64).reshape(-1, 2)
        if len(lib) < 3:
            continue
        area_lib, centroid_lib = polygon_area_centroid(lib)
        if abs(area_lib) > 0:
            size_term = abs(math.log(area_det / abs(area_lib)))
            candidates.append((size_term, workpiece_id, lib, abs(area_lib), centroid_lib))
    # likeliest first (closest in size), so the others can be skipped on size alone
    candidates.sort(key=lambda c: c[0])
    best: OutlineMatch | None = None
    for size_term, workpiece_id, lib, area_lib, centroid_lib in candidates:
        bound = max_score if best is None else min(max_score, best.score)
        if size_term >= bound:
            break
        rotation, shift, fit_error = _fit_rigid(lib, detected)
        score = fit_error / math.sqrt(area_lib) + size_term
        if score >= bound:
            continue
        a = math.radians(rotation)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        transform = np.hstack([rot, (centroid_lib - rot @ centroid_lib + shift)[:, None]])
        best = OutlineMatch(
            workpiece_id,
            float(score),
            float(rotation),
            (float(shift[0]), float(shift[1])),
            transform,
            float(fit_error),
        )
    return best


# --- rigid fit (point-to-line ICP) ----------------------------------------------------------

_COARSE_POINTS, _FINE_POINTS = 64, 256
_SWEEP_DEG = 30.0  # starting angles every 30°: ICP pulls in from ±15° for any symmetry ≥ 60°
_TIE_RELATIVE, _TIE_ABSOLUTE_MM = 0.05, 0.02
_CLEAR_AXIS = 0.2  # anisotropy above which the principal axis alone gives the starting turn


def _rotation(angle_rad: float) -> Array:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


def _closest_on_polygon(points: Array, polygon: Array) -> tuple[Array, Array]:
    """Closest point on a closed polygon's edges for each point, and the unit normal there.

    Written on separate x and y planes (M×K each): the matcher spends most of its time here.
    """
    ax, ay = polygon[:, 0], polygon[:, 1]
    abx, aby = np.roll(ax, -1) - ax, np.roll(ay, -1) - ay
    inv_length2 = 1.0 / np.maximum(abx * abx + aby * aby, 1e-18)
    rx = points[:, 0:1] - ax
    ry = points[:, 1:2] - ay
    t = np.clip((rx * abx + ry * aby) * inv_length2, 0.0, 1.0)
    dx = rx - t * abx
    dy = ry - t * aby
    index = np.argmin(dx * dx + dy * dy, axis=1)
    rows = np.arange(len(points))
    away = np.column_stack([dx[rows, index], dy[rows, index]])
    closest = points - away
    norm = np.hypot(away[:, 0], away[:, 1])[:, None]
    scale = np.sqrt(inv_length2[index])[:, None]
    edge_normal = np.column_stack([-aby[index], abx[index]]) * scale
    normal = np.where(norm > 1e-9, away / np.maximum(norm, 1e-300), edge_normal)
    return closest, normal


def _icp(
    points: Array, polygon: Array, rot: Array, shift: Array, iterations: int
) -> tuple[Array, Array, float]:
    """Refine S(p) = rot·p + shift so that S(points) lies on `polygon` (point-to-line ICP).

    Returns the refined rot, shift and the RMS point-to-polygon distance.
    """
    previous = math.inf
    for _ in range(iterations):
        moved = points @ rot.T + shift
        closest, normal = _closest_on_polygon(moved, polygon)
        residual = ((moved - closest) * normal).sum(axis=1)
        rms = float(np.sqrt((residual**2).mean()))
        if previous - rms < 1e-6:  # no longer improving (also ends a damped, free turn)
            break
        previous = rms
        centre = moved.mean(axis=0)
        lever = moved - centre
        jac = np.column_stack([normal, normal[:, 1] * lever[:, 0] - normal[:, 0] * lever[:, 1]])
        normal_eq = jac.T @ jac
        # damping: a turn the outline does not constrain (a disc) stays where it started
        damping = 1e-9 * np.trace(normal_eq) + 1e-12
        normal_eq += np.diag([damping, damping, damping + 1e-3 * float((lever**2).sum())])
        step = np.linalg.solve(normal_eq, -jac.T @ residual)
        turn = float(np.clip(step[2], -0.3, 0.3))
        d_rot = _rotation(turn)
        rot = d_rot @ rot
        shift = d_rot @ (shift - centre) + centre + step[:2]
        if abs(turn) < 1e-8 and float(np.hypot(step[0], step[1])) < 1e-6:
            break
    moved = points @ rot.T + shift
    closest, _ = _closest_on_polygon(moved, polygon)
    rms = float(np.sqrt(((moved - closest) ** 2).sum(axis=1).mean()))
    return rot, shift, rms


def _fit_rigid(library: Array, detected: Array) -> tuple[float, Array, float]:
    """Turn (°, CCW) and centroid shift (mm) taking `library` onto `detected`, and the RMS
    distance between the aligned outlines (both ways, so neither can hide a missing feature).

    ICP runs detected → library (the library polygon is the cleaner target) from the
    principal-axis angles ±180° and a sweep every 30°. Symmetric parts converge to several
    equally good solutions; the best one and the smallest turn among the near-best are
    refined on denser points, and the smallest turn wins a tie.
    """
    library = _simplified(library)
    _, c_lib = polygon_area_centroid(library)
    _, c_det = polygon_area_centroid(detected)
    axis_turn = outline_pose(library).theta_deg - outline_pose(detected).theta_deg
    starts = [axis_turn, axis_turn + 180.0]
    if min(_anisotropy(library), _anisotropy(detected)) < _CLEAR_AXIS:
        starts += list(np.arange(0.0, 360.0, _SWEEP_DEG))  # principal axes say little
    coarse = resample_closed(detected, _COARSE_POINTS)
    solutions = []
    for start in starts:
        rot = _rotation(math.radians(start))
        rot, shift, rms = _icp(coarse, library, rot, c_lib - rot @ c_det, iterations=10)
        solutions.append((rms, _turn_deg(rot), rot, shift))
    best_rms = min(s[0] for s in solutions)
    near = [s for s in solutions if s[0] <= 1.5 * best_rms + 0.05]
    picks = {
        id(min(solutions, key=lambda s: s[0])): None,
        id(min(near, key=lambda s: abs(s[1]))): None,
    }
    fine = resample_closed(detected, _FINE_POINTS)
    fine_lib = resample_closed(library, _FINE_POINTS)
    results = []
    for _, _, rot, shift in (s for s in solutions if id(s) in picks):
        rot, shift, rms_forward = _icp(fine, library, rot, shift, iterations=40)
        # library → detected is the inverse transform: rot⁻¹ (p − shift)
        back = (fine_lib - shift) @ rot
        closest, _ = _closest_on_polygon(back, detected)
        rms_back = float(np.sqrt(((back - closest) ** 2).sum(axis=1).mean()))
        error = math.sqrt(0.5 * (rms_forward**2 + rms_back**2))
        results.append((error, _turn_deg(rot), rot, shift))
    tolerance = min(r[0] for r in results) * (1.0 + _TIE_RELATIVE) + _TIE_ABSOLUTE_MM
    error, turn, rot, shift = min(
        (r for r in results if r[0] <= tolerance), key=lambda r: abs(r[1])
    )
    moved_centroid = (c_lib - shift) @ rot  # where the library centroid lands
    return turn, moved_centroid - c_lib, error


def _anisotropy(outline: Array) -> float:
    """(λ1 − λ2) / (λ1 + λ2) of the area's inertia: 0 for a square or disc, →1 for a bar."""
    _, centroid = polygon_area_centroid(outline)
    ixx, iyy, ixy = _second_moments(outline, centroid)
    return math.hypot(ixx - iyy, 2.0 * ixy) / max(abs(ixx + iyy), 1e-300)


def _turn_deg(rot: Array) -> float:
    """The library → detected turn of a detected → library rotation matrix, in (-180°, 180°]."""
    return _wrap_deg(-math.degrees(math.atan2(rot[1, 0], rot[0, 0])))


def _simplified(outline: Array) -> Array:
    """A dense library outline (a 180-gon disc) thinned to ~0.05 mm: ICP cost is per vertex."""
    if len(outline) <= 64:
        return outline
    thin = cv2.approxPolyDP(outline.astype(np.float32).reshape(-1, 1, 2), 0.05, True)
    return _nearest_points(outline, thin.reshape(-1, 2).astype(np.float64))


def _wrap_deg(angle_deg: float) -> float:
    """Into (-180°, 180°]."""
    wrapped = (angle_deg + 180.0) % 360.0 - 180.0
    return 180.0 if wrapped == -180.0 else wrapped

"""Spray paths on a workpiece: an offset outline bead and a line fill, in table millimetres.

Everything the robot sprays is a polyline along which the glue flows continuously; between
polylines the valve closes and the robot travels. The order is what the robot executes: the
bead along the (offset) outline first, so the fill never smears it, then the fill.

The outline offset is a mitred offset (the bead keeps the part's sharp corners at a constant
distance from every edge) that stays correct for concave parts: an edge that shrinks away as
the outline moves inward (a short chamfer, the inside of a narrow notch) is dropped and its
neighbours meet directly, which is what a true offset does. An offset that would split the
part or make it vanish raises ValueError rather than return a self-crossing path.

Fill lines are scan lines clipped to the polygon and ordered boustrophedon per cell of the
part (a concave part is filled region by region, not by jumping across a notch on every
line); with `zigzag` neighbouring lines are joined into one polyline wherever the join stays
on the part, so the valve does not switch at every line.

Planning can be stopped: each function takes a `checkpoint`, called once per pass of its
loops (an offset step, a scan line, a cell, a join). It returns to carry on or raises to
stop; what it raises comes out of the planner unchanged. Why: the planner runs in a thread,
and a thread cannot be cancelled from outside; a run that is cancelled or out of time stops
the planning at its next checkpoint (milliseconds) instead of leaving it running. `fill_size`
counts a fill's lines and straight strokes without planning it, cheaply enough to refuse a
part whose fill would take too long to plan and spray.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "Checkpoint",
    "SprayPattern",
    "fill_lines",
    "fill_size",
    "offset_polygon",
    "spray_polylines",
]

Array = NDArray[np.float64]
Checkpoint = Callable[[], None]  # returns to carry on, raises to stop the planning


def _carry_on() -> None:
    """The default checkpoint: planning runs to its end."""


FILL_KINDS = ("none", "zigzag", "raster")
MITRE_LIMIT = 4.0  # a corner sharper than this (mitre / offset) is bevelled, not spiked
_EPS = 1e-9


@dataclass(frozen=True)
class SprayPattern:
    """How to spray one workpiece (all lengths mm, angles ° from robot +x, CCW)."""

    outline_offset_mm: float = 0.0  # >0 grows outward, <0 inward
    outline: bool = True
    fill: str = "none"  # "none" | "zigzag" | "raster"
    fill_spacing_mm: float = 10.0
    fill_angle_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.fill not in FILL_KINDS:
            raise ValueError(f"fill must be one of {', '.join(FILL_KINDS)}, got {self.fill!r}")
        if self.fill != "none" and not self.fill_spacing_mm > 0:
            raise ValueError(f"fill_spacing_mm must be positive, got {self.fill_spacing_mm}")


# --- polygon helpers -------------------------------------------------------------------------


def _signed_area(pts: Array) -> float:
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())


def clean_outline(outline: ArrayLike) -> Array:
    """Open, counter-clockwise, without repeated or collinear vertices."""
    pts = np.asarray(outline, dtype=np.float64).reshape(-1, 2)
    if len(pts) > 1 and np.allclose(pts[0], pts[-1]):
        pts = pts[:-1]
    changed = True
    while changed and len(pts) >= 3:
        changed = False
        prev, nxt = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
        d_in, d_out = pts - prev, nxt - pts
        cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
        scale = np.linalg.norm(d_in, axis=1) * np.linalg.norm(d_out, axis=1)
        degenerate = (np.linalg.norm(d_out, axis=1) < 1e-9) | (
            (np.abs(cross) <= 1e-9 * np.maximum(scale, 1e-300)) & ((d_in * d_out).sum(axis=1) >= 0)
        )
        if degenerate.any():
            drop = int(np.argmax(degenerate))  # one at a time: neighbours change
            pts = np.delete(pts, drop, axis=0)
            changed = True
    if len(pts) < 3:
        raise ValueError("an outline needs at least three distinct, non-collinear points")
    if _signed_area(pts) < 0:
        pts = pts[::-1].copy()
    return pts


def simple_outline(outline_mm: ArrayLike) -> Array:
    """The outline as `clean_outline` gives it, refused (ValueError) when two of its edges cross.

    A part's outline goes round it once: one that crosses itself (a bow-tie, points
    typed in the wrong order) has no inside to fill and no side to offset the bead to.
    """
    pts = clean_outline(outline_mm)
    if _self_intersects(pts):
        raise ValueError(
            "the outline crosses itself: list the points in order around the part, "
            "so that no two edges cross"
        )
    return pts


def _orient(u: Array, v: Array, w: Array) -> Array:
    """Twice the signed area of triangles (u, v, w), broadcasting over leading axes."""
    return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (
        w[..., 0] - u[..., 0]
    )


def _crosses(p: Array, q: Array, a: Array, b: Array) -> NDArray[np.bool_]:
    """Where segments p→q and a→b cross properly (touching at an end does not count)."""
    scale = max(1.0, float(np.abs(np.concatenate([p.ravel(), q.ravel(), a.ravel()])).max()))
    tol = 1e-9 * scale * scale
    d1, d2 = _orient(a, b, p), _orient(a, b, q)
    d3, d4 = _orient(p, q, a), _orient(p, q, b)
    return (((d1 > tol) & (d2 < -tol)) | ((d1 < -tol) & (d2 > tol))) & (
        ((d3 > tol) & (d4 < -tol)) | ((d3 < -tol) & (d4 > tol))
    )


def _self_intersects(pts: Array) -> bool:
    """True if any two non-neighbouring edges of the closed polygon cross."""
    n = len(pts)
    a, b = pts, np.roll(pts, -1, axis=0)
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # the last and first edge share a vertex
    i, j = i[keep], j[keep]
    if not len(i):  # a triangle: every two edges share a vertex, none can cross
        return False
    return bool(_crosses(a[i], b[i], a[j], b[j]).any())


def _distances(points: Array, polygon: Array) -> Array:
    """Distance from each point to the polygon's boundary."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    ab = b - a
    rel = points[:, None, :] - a[None]
    t = np.clip((rel * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    distances: Array = np.linalg.norm(rel - t[..., None] * ab, axis=-1).min(axis=1)
    return distances


def _inside(pts: Array, point: Array) -> bool:
    """Point in polygon (even-odd); points on the boundary may go either way."""
    x, y = point
    xi, yi = pts[:, 0], pts[:, 1]
    xj, yj = np.roll(xi, 1), np.roll(yi, 1)
    crosses = (yi > y) != (yj > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = xi + (y - yi) * (xj - xi) / (yj - yi)
    return bool(np.count_nonzero(crosses & (x < at)) % 2)


# --- offset ----------------------------------------------------------------------------------


def _offset_vertices(points: Array, dirs: Array, offset: float) -> Array | None:
    """Intersections of consecutive offset edge lines; None if two neighbours are parallel."""
    normals = np.stack([dirs[:, 1], -dirs[:, 0]], axis=1)  # outward for a CCW polygon
    base = points + offset * normals  # a point on each offset line
    prev_base, prev_dir = np.roll(base, 1, axis=0), np.roll(dirs, 1, axis=0)
    # solve prev_base + s·prev_dir = base + t·dir for each vertex
    denom = prev_dir[:, 0] * dirs[:, 1] - prev_dir[:, 1] * dirs[:, 0]
    if np.any(np.abs(denom) < 1e-12):
        return None
    diff = base - prev_base
    s = (diff[:, 0] * dirs[:, 1] - diff[:, 1] * dirs[:, 0]) / denom
    return prev_base + s[:, None] * prev_dir


def offset_polygon(
    outline_mm: np.ndarray, offset_mm: float, *, checkpoint: Checkpoint = _carry_on
) -> Array:
    """The outline moved `offset_mm` outward (>0) or inward (<0), mitred, counter-clockwise.

    Raises ValueError when an inward offset makes the part vanish or split, or an outward
    offset makes the outline run into itself.
    """
    pts = clean_outline(outline_mm)
    offset = float(offset_mm)
    if abs(offset) < 1e-9:
        return pts.copy()
    # the polygon as edge lines: a point and a unit direction each
    lines_p = pts.copy()
    lines_d = np.roll(pts, -1, axis=0) - pts
    lines_d /= np.linalg.norm(lines_d, axis=1, keepdims=True)
    while True:
        checkpoint()
        if len(lines_p) < 3:
            raise ValueError(_too_far(offset))
        verts = _offset_vertices(lines_p, lines_d, offset)
        if verts is None:
            raise ValueError(_too_far(offset))
        base = _offset_vertices(lines_p, lines_d, 0.0)
        assert base is not None
        span = np.roll(verts, -1, axis=0) - verts
        new_len = (span * lines_d).sum(axis=1)  # signed: negative when the edge turned over
        old_len = ((np.roll(base, -1, axis=0) - base) * lines_d).sum(axis=1)
        reversed_ = new_len < -_EPS
        if not reversed_.any():
            break
        # drop the edge that vanished first (smallest offset at which its length is zero)
        rate = (old_len - new_len) / abs(offset)
        with np.errstate(divide="ignore", invalid="ignore"):
            vanish_at = np.where(reversed_ & (rate > 0), old_len / rate, np.inf)
        drop = int(np.argmin(vanish_at))
        lines_p = np.delete(lines_p, drop, axis=0)
        lines_d = np.delete(lines_d, drop, axis=0)
    result = _bevel(verts, base, lines_d, offset)
    if _signed_area(result) <= 0 or not _keeps_distance(pts, result, abs(offset)):
        raise ValueError(_too_far(offset))
    return result


def _keeps_distance(original: Array, result: Array, distance: float) -> bool:
    """A true offset keeps every point at least `distance` from the original outline.

    Where two parts of the offset outline have run into each other (the part split, a notch
    closed), points come closer than that, or edges cross: either means no valid offset.
    """
    if _self_intersects(result):
        return False
    ends = np.roll(result, -1, axis=0)
    t = np.linspace(0.0, 1.0, 9)[:-1]
    samples = (result[:, None, :] + t[None, :, None] * (ends - result)[:, None, :]).reshape(-1, 2)
    return bool(np.all(_distances(samples, original) >= distance * (1.0 - 1e-6) - 1e-9))


def _too_far(offset: float) -> str:
    if offset < 0:
        return (
            f"an inward offset of {-offset:g} mm makes the outline vanish or split (the part "
            "is narrower than twice the offset somewhere); use a smaller offset"
        )
    return (
        f"an outward offset of {offset:g} mm makes the outline run into itself (a notch or "
        "gap narrower than twice the offset closes); use a smaller offset"
    )


def _bevel(verts: Array, corners: Array, dirs: Array, offset: float) -> Array:
    """Cut spikes at very sharp opening corners square to the bisector, |offset| out."""
    prev_dir = np.roll(dirs, 1, axis=0)
    cross = prev_dir[:, 0] * dirs[:, 1] - prev_dir[:, 1] * dirs[:, 0]
    cos_turn = (prev_dir * dirs).sum(axis=1)
    mitre = 1.0 / np.sqrt(np.maximum((1.0 + cos_turn) / 2.0, 1e-12))  # mitre length / offset
    out = []
    for i, vertex in enumerate(verts):
        d_in, d_out = prev_dir[i], dirs[i]
        if offset * cross[i] > 0 and mitre[i] > MITRE_LIMIT and abs(d_in @ d_out) < 1 - 1e-12:
            n_in, n_out = np.array([d_in[1], -d_in[0]]), np.array([d_out[1], -d_out[0]])
            bisector = n_in + n_out
            bisector *= np.sign(offset) / np.linalg.norm(bisector)
            # on each offset line, the point whose distance along the bisector is |offset|
            for normal, direction in ((n_in, d_in), (n_out, d_out)):
                along = (abs(offset) - offset * (normal @ bisector)) / (direction @ bisector)
                out.append(corners[i] + offset * normal + along * direction)
        else:
            out.append(vertex)
    return np.asarray(out, dtype=np.float64)


# --- fill ------------------------------------------------------------------------------------


def _scan_ys(pts: Array, spacing: float) -> Array:
    """The scan lines' y (local frame), centred on the part, `spacing` apart."""
    y_min, y_max = float(pts[:, 1].min()), float(pts[:, 1].max())
    count = max(1, math.floor((y_max - y_min) / spacing + 1e-9))
    middle = 0.5 * (y_min + y_max)
    return np.asarray(middle + (np.arange(count) - (count - 1) / 2.0) * spacing, dtype=np.float64)


def _scan_segments(
    pts: Array, spacing: float, checkpoint: Checkpoint = _carry_on
) -> list[list[tuple[float, float, float]]]:
    """Per scan line (bottom to top), the (y, x_start, x_end) inside the polygon."""
    a, b = pts, np.roll(pts, -1, axis=0)
    rows: list[list[tuple[float, float, float]]] = []
    for y in _scan_ys(pts, spacing):
        checkpoint()
        crosses = ((a[:, 1] <= y) & (y < b[:, 1])) | ((b[:, 1] <= y) & (y < a[:, 1]))
        if not crosses.any():
            rows.append([])
            continue
        pa, pb = a[crosses], b[crosses]
        xs = np.sort(pa[:, 0] + (y - pa[:, 1]) * (pb[:, 0] - pa[:, 0]) / (pb[:, 1] - pa[:, 1]))
        rows.append(
            [
                (float(y), float(xs[k]), float(xs[k + 1]))
                for k in range(0, len(xs) - 1, 2)
                if xs[k + 1] - xs[k] > 1e-6
            ]
        )
    return rows


def _cells(
    rows: list[list[tuple[float, float, float]]], checkpoint: Checkpoint = _carry_on
) -> list[list[tuple[float, float, float]]]:
    """Group segments into cells: runs of lines where each segment overlaps exactly one
    segment on the next line and vice versa (a boustrophedon decomposition)."""
    cells: list[list[tuple[float, float, float]]] = []
    open_cells: list[int] = []  # index into cells, one per segment of the previous row
    previous: list[tuple[float, float, float]] = []
    for row in rows:
        checkpoint()
        # which segments of the previous row each one overlaps (vectorised: a row of a
        # toothed part has hundreds of segments, and this ran between two checkpoints)
        if row and previous:
            here, before = np.asarray(row), np.asarray(previous)
            overlap = np.minimum(here[:, None, 2], before[None, :, 2]) > np.maximum(
                here[:, None, 1], before[None, :, 1]
            )
            links = [np.flatnonzero(line).tolist() for line in overlap]
            back = overlap.sum(axis=0).tolist()
        else:
            links, back = [[] for _ in row], [0] * len(previous)
        next_open = []
        for segment, link in zip(row, links, strict=True):
            if len(link) == 1 and back[link[0]] == 1:
                cell = open_cells[link[0]]
                cells[cell].append(segment)
            else:
                cells.append([segment])
                cell = len(cells) - 1
            next_open.append(cell)
        open_cells, previous = next_open, row
    return cells


def fill_lines(
    outline_mm: np.ndarray,
    spacing_mm: float,
    angle_deg: float = 0.0,
    *,
    zigzag: bool = True,
    start: ArrayLike | None = None,
    checkpoint: Checkpoint = _carry_on,
) -> list[Array]:
    """Scan lines at `angle_deg`, `spacing_mm` apart, clipped to the polygon, in spray order.

    Lines are centred on the part (the outermost lie half a spacing or more inside its
    extent). Without `zigzag` each is a 2×2 segment; with it, consecutive lines are joined
    into one polyline where the join stays inside the part. `start` (mm) is where the robot
    is when the fill begins (default: the first line's start); cells begin at the end
    nearest to it.
    """
    if not spacing_mm > 0:
        raise ValueError(f"fill spacing must be positive, got {spacing_mm}")
    pts = clean_outline(outline_mm)
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    local = pts @ rot  # rotate by -angle: scan lines run along local x
    cells = _cells(_scan_segments(local, float(spacing_mm), checkpoint), checkpoint)
    here = None if start is None else np.asarray(start, dtype=np.float64).reshape(2) @ rot
    ordered: list[Array] = []
    # Each cell's four ways in: (first or last segment) × (left or right end), as (x, y).
    ends = np.array(
        [
            [(c[0][1], c[0][0]), (c[0][2], c[0][0]), (c[-1][1], c[-1][0]), (c[-1][2], c[-1][0])]
            for c in cells
        ],
        dtype=np.float64,
    ).reshape(-1, 4, 2)
    ways = ((False, True), (False, False), (True, True), (True, False))  # from_top, left_first
    left = np.ones(len(cells), dtype=bool)
    for _ in range(len(cells)):
        checkpoint()
        # next cell: the one with an end segment nearest to where we are (the first of
        # those within 1e-9 mm, in cell order); vectorised, so many cells stay cheap
        live = np.flatnonzero(left)
        choice = 0
        if here is not None:
            near = ends[live]
            d = np.hypot(near[..., 0] - here[0], near[..., 1] - here[1]).ravel()
            choice = int(np.flatnonzero(d <= d.min() + 1e-9)[0])
        index = int(live[choice // 4])
        from_top, left_first = ways[choice % 4]
        left[index] = False
        sequence = cells[index][::-1] if from_top else cells[index]
        for seg in sequence:
            y, x0, x1 = seg
            line = np.array([[x0, y], [x1, y]]) if left_first else np.array([[x1, y], [x0, y]])
            ordered.append(line)
            left_first = not left_first
        here = ordered[-1][1]
    segments = [line @ rot.T for line in ordered]
    if not zigzag:
        return segments
    polylines: list[Array] = []
    for seg in segments:
        checkpoint()
        if polylines and _join_inside(pts, polylines[-1][-1], seg[0]):
            polylines[-1] = np.vstack([polylines[-1], seg])
        else:
            polylines.append(seg.copy())
    return polylines


def _join_inside(pts: Array, p: Array, q: Array) -> bool:
    """True if the straight move p → q stays on the part (it may run along the edge)."""
    if float(np.linalg.norm(q - p)) < 1e-9:
        return True
    if _crosses(p[None], q[None], pts, np.roll(pts, -1, axis=0)).any():
        return False
    for t in (0.25, 0.5, 0.75):
        probe = p + t * (q - p)
        if not _inside(pts, probe) and float(_distances(probe[None], pts)[0]) > 1e-6:
            return False
    return True


# --- the whole pattern -----------------------------------------------------------------------


def spray_polylines(
    outline_mm: np.ndarray, pattern: SprayPattern, *, checkpoint: Checkpoint = _carry_on
) -> list[Array]:
    """The polylines (M×2 mm) along which glue flows, in execution order.

    First the bead along the outline at `outline_offset_mm` (closed: last point = first),
    if `pattern.outline`; then the fill lines. The fill covers the part inside the bead: the
    inward-offset outline, or the part's own outline when the bead is on or outside it (glue
    is never filled onto the table).
    """
    outline = simple_outline(outline_mm)
    bead = offset_polygon(outline, pattern.outline_offset_mm, checkpoint=checkpoint)
    paths: list[Array] = []
    if pattern.outline:
        paths.append(np.vstack([bead, bead[:1]]))
    if pattern.fill != "none":
        region = bead if pattern.outline_offset_mm < 0 else outline
        start = paths[-1][-1] if paths else None
        paths.extend(
            fill_lines(
                region,
                pattern.fill_spacing_mm,
                pattern.fill_angle_deg,
                zigzag=pattern.fill == "zigzag",
                start=start,
                checkpoint=checkpoint,
            )
        )
    return paths


def fill_size(
    outline_mm: np.ndarray, spacing_mm: float, angle_deg: float = 0.0, *, max_lines: int
) -> tuple[int, int | None]:
    """The fill's scan lines and straight strokes (lines × crossings / 2), without planning it.

    One vectorised pass over lines × edges. The strokes of a fill of more than `max_lines`
    lines are not counted (None): the count itself would then cost what it is there to
    prevent.
    """
    if not spacing_mm > 0:
        raise ValueError(f"fill spacing must be positive, got {spacing_mm}")
    pts = clean_outline(outline_mm)
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    local = pts @ rot  # as fill_lines: scan lines run along local x
    extent = float(local[:, 1].max() - local[:, 1].min())
    lines = max(1, math.floor(extent / float(spacing_mm) + 1e-9))
    if lines > max_lines:
        return lines, None
    ys = _scan_ys(local, float(spacing_mm))[:, None]
    ya, yb = local[None, :, 1], np.roll(local, -1, axis=0)[None, :, 1]
    crosses = ((ya <= ys) & (ys < yb)) | ((yb <= ys) & (ys < ya))
    return lines, int((crosses.sum(axis=1) // 2).sum())

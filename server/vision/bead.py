"""Bead inspection: find the glue bead along each planned spray segment and judge it.

The inspection sees only the (undistorted) frame and the plan. Along each planned polyline,
every ~1 mm, a profile is sampled across the path on the table (through the calibration's
`to_pixels`, so the profile is in mm whatever the camera's perspective). The glue is an amber
bead on a neutral part (grey aluminium on a grey table), so the profile is read in red minus
blue: the part, the table and the light's colour-neutral variations (vignetting, gradients,
uneven light) all read near zero there and the glue reads high. In each profile the bead is
the run above half the bead's contrast that is nearest the path; its width is the run's
integrated contrast over the full contrast (the area under the profile, exact under blur and
sub-pixel edges), its centre the contrast's centroid. Profiles without that run are gaps.

Judged against the tolerances (`BeadTolerances`, from the Quality settings):
- width: the segment's mean width, and any stretch longer than `WIDTH_STRETCH_MM` whose
  running median is out of tolerance (a nozzle that clogs half-way);
- gaps: the longest stretch without bead;
- offset: the bead's centre from the planned line, sustained over `OFFSET_RUN` samples so a
  single noisy profile never fails a part.
Profiles close to a sharp corner of the path measure the other leg's bead as well, so they
count for gaps only.

The expected width follows flow over speed (`expected_bead_width_mm`): the glue leaving the
nozzle each second is laid over `speed` mm of path, as a bead whose cross-section is half an
ellipse twice as wide as it is high. The simulated camera renders the dispensed bead with the
same function, so the inspection and the simulator agree on the physics, not on the result.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from server.vision.homography import PlaneCalibration

__all__ = [
    "BeadSegment",
    "BeadTolerances",
    "SegmentBead",
    "annotate_bead",
    "expected_bead_width_mm",
    "inspect_bead",
]

STEP_MM = 1.0  # spacing of the profiles along the path
PROFILE_STEP_MM = 0.25  # spacing of the samples across it
# The glue's red-minus-blue contrast against the part per grey level of the part's brightness,
# as taught for the cell's amber glue on aluminium (light scales both alike). A thin bead's
# own peak falls short of its full contrast (blur, and JPEG's halved colour resolution), so
# the full contrast is never taken below this times the part's brightness beside the bead.
GLUE_CONTRAST_PER_LUMA = 0.74
GLUE_CONTRAST_MIN = 35.0  # red minus blue (grey levels) below which no glue is seen at all
PRESENT_FRACTION = 0.4  # a profile whose bead is narrower than this × expected is a gap
WIDTH_STRETCH_MM = 10.0  # a width out of tolerance over a longer stretch is a defect
OFFSET_RUN = 3  # consecutive profiles an offset must hold to count
CORNER_TURN_DEG = 30.0  # a turn sharper than this makes its neighbourhood a corner
CROWD_MARGIN_MM = 3.0  # beyond touching, where another segment's bead may still merge


def expected_bead_width_mm(flow_ml_min: float, speed_mm_s: float) -> float:
    """The bead's width (mm) for glue leaving at `flow_ml_min` with the nozzle at `speed_mm_s`.

    The cross-section (mm²) is the volume per mm of path, flow (mm³/s) over speed (mm/s);
    the bead is taken as half an ellipse of height width/2, area π/8·width². So the width
    follows the square root of flow over speed: 30 ml/min at 100 mm/s gives 3.6 mm.
    """
    if speed_mm_s <= 0:
        raise ValueError(f"speed_mm_s must be > 0, got {speed_mm_s}")
    if flow_ml_min <= 0:
        return 0.0
    area_mm2 = flow_ml_min * 1000.0 / 60.0 / speed_mm_s
    return math.sqrt(8.0 * area_mm2 / math.pi)


@dataclass(frozen=True)
class BeadSegment:
    """One planned spray segment: 1-based `index` in plan order, its polyline in table mm."""

    index: int
    workpiece_id: str
    path_mm: np.ndarray  # (N, 2) robot/table x, y mm
    expected_width_mm: float


@dataclass(frozen=True)
class BeadTolerances:
    """How far a bead may depart from its plan before the part is defective."""

    width_tolerance_percent: float
    max_gap_mm: float
    max_offset_mm: float

    @classmethod
    def from_settings(cls, settings: Any) -> BeadTolerances:
        """The Quality settings' bead tolerances (bead_width_tolerance_percent, ...)."""
        return cls(
            width_tolerance_percent=float(settings.bead_width_tolerance_percent),
            max_gap_mm=float(settings.bead_max_gap_mm),
            max_offset_mm=float(settings.bead_max_offset_mm),
        )


@dataclass
class SegmentBead:
    """What was found along one segment; `problems` empty means its bead is good.

    `trace` (not part of `as_dict`) keeps each profile's finding for `annotate_bead`: rows of
    (x mm, y mm of the bead's centre, or of the path where no bead was found; width mm or
    NaN; 1 if a bead was found, 0 for a gap, -1 where the camera did not see the path).
    """

    index: int
    workpiece_id: str
    length_mm: float
    width_mean_mm: float | None
    width_min_mm: float | None
    width_max_mm: float | None
    gaps_mm: list[tuple[float, float]]
    longest_gap_mm: float
    offset_mean_mm: float | None
    offset_max_mm: float | None
    problems: list[str]
    trace: NDArray[np.float64] | None = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, figures rounded to 0.01 mm."""

        def mm(value: float | None) -> float | None:
            return None if value is None else round(float(value), 2)

        return {
            "index": self.index,
            "workpiece_id": self.workpiece_id,
            "length_mm": mm(self.length_mm),
            "width_mean_mm": mm(self.width_mean_mm),
            "width_min_mm": mm(self.width_min_mm),
            "width_max_mm": mm(self.width_max_mm),
            "gaps_mm": [[mm(a), mm(b)] for a, b in self.gaps_mm],
            "longest_gap_mm": mm(self.longest_gap_mm),
            "offset_mean_mm": mm(self.offset_mean_mm),
            "offset_max_mm": mm(self.offset_max_mm),
            "problems": list(self.problems),
        }


# --- sampling the profiles ---------------------------------------------------------------


@dataclass(frozen=True)
class _Stations:
    """Where the profiles are taken: along-path distance, point, unit normal, near a corner."""

    along: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    corner: NDArray[np.bool_]  # near a sharp turn or another segment's bead: gaps only
    length: float


def _stations(path: NDArray[np.float64], corner_zone_mm: float) -> _Stations:
    pieces = np.diff(path, axis=0)
    lengths = np.hypot(pieces[:, 0], pieces[:, 1])
    keep = lengths > 1e-9
    pieces, lengths = pieces[keep], lengths[keep]
    starts = path[:-1][keep]
    total = float(lengths.sum())
    if total <= 0:
        empty = np.zeros((0, 2))
        return _Stations(np.zeros(0), empty, empty, np.zeros(0, bool), 0.0)
    count = max(1, math.ceil(total / STEP_MM - 1e-9))
    along = (np.arange(count, dtype=np.float64) + 0.5) * (total / count)
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    piece = np.clip(np.searchsorted(cumulative, along, side="right") - 1, 0, len(lengths) - 1)
    direction = pieces[piece] / lengths[piece, None]
    points = starts[piece] + direction * (along - cumulative[piece])[:, None]
    normals = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    # corners: interior vertices (and the closing one of a closed path) that turn sharply
    # sharp turns: interior vertices (and the closing one of a closed path); the two legs'
    # beads run together over (zone / sin(half the angle between them)) of each
    turns: list[tuple[float, float]] = []
    headings = np.arctan2(pieces[:, 1], pieces[:, 0])

    def turn_at(before: float, after: float) -> float:
        return abs((after - before + math.pi) % (2 * math.pi) - math.pi)

    for k in range(1, len(headings)):
        turns.append((float(cumulative[k]), turn_at(headings[k - 1], headings[k])))
    closed = len(headings) > 1 and float(np.hypot(*(path[-1] - path[0]))) < 1e-6
    if closed:
        turn = turn_at(headings[-1], headings[0])
        turns.extend([(0.0, turn), (total, turn)])
    corner = np.zeros(count, dtype=bool)
    for at, turn in turns:
        if math.degrees(turn) > CORNER_TURN_DEG:
            reach = corner_zone_mm / max(math.cos(turn / 2.0), 0.15)
            corner |= np.abs(along - at) < reach
    return _Stations(along, points, normals, corner, total)


def _distance_to_polyline(
    points: NDArray[np.float64], path: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Each point's distance (mm) to the polyline `path`."""
    if len(path) == 1:
        return np.asarray(np.hypot(*(points - path[0]).T), dtype=np.float64)
    a, b = path[:-1], path[1:]
    ab = b - a
    span = np.maximum((ab**2).sum(axis=1), 1e-12)
    t = np.clip(((points[:, None, :] - a[None]) * ab[None]).sum(axis=2) / span, 0.0, 1.0)
    nearest = a[None] + t[..., None] * ab[None]
    return np.asarray(np.hypot(*(points[:, None, :] - nearest).transpose(2, 0, 1)).min(axis=1))


def _crowded(
    stations: _Stations, segment: BeadSegment, others: Sequence[BeadSegment]
) -> NDArray[np.bool_]:
    """Stations where another segment's bead meets or crosses this one: the profile there
    measures both beads together, so it counts for gaps only."""
    crowded = np.zeros(len(stations.along), dtype=bool)
    for other in others:
        path = np.asarray(other.path_mm, dtype=np.float64).reshape(-1, 2)
        if not len(path) or not len(stations.along):
            continue
        # beads meeting at a slant run together over a few mm more than where they touch
        reach = (segment.expected_width_mm + other.expected_width_mm) / 2.0 + CROWD_MARGIN_MM
        crowded |= _distance_to_polyline(stations.points, path) < reach
    return crowded


def _profiles(
    frame: NDArray[np.uint8],
    stations: _Stations,
    offsets: NDArray[np.float64],
    calibration: PlaneCalibration,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Red minus blue across the path at each station (stations × offsets), the grey level
    there, and which stations the camera saw (the station's point inside the frame)."""
    grid = stations.points[:, None, :] + offsets[None, :, None] * stations.normals[:, None, :]
    pixels = calibration.to_pixels(grid.reshape(-1, 2)).reshape(grid.shape)
    map_x = np.ascontiguousarray(pixels[..., 0], dtype=np.float32)
    map_y = np.ascontiguousarray(pixels[..., 1], dtype=np.float32)
    sampled = cv2.remap(
        frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    ).astype(np.float32)
    height, width = frame.shape[:2]
    centre = pixels[:, len(offsets) // 2]
    seen = (
        (centre[:, 0] >= 0) & (centre[:, 0] <= width - 1)
        & (centre[:, 1] >= 0) & (centre[:, 1] <= height - 1)
    )  # fmt: skip
    luma = sampled @ np.array([0.114, 0.587, 0.299], dtype=np.float32)
    return sampled[..., 2] - sampled[..., 0], luma, seen


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """[start, end) index ranges where `mask` is true."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _measure(
    profiles: NDArray[np.float32], luma: NDArray[np.float32], offsets: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each profile's bead width (mm, NaN: none) and centre offset (mm, NaN: none)."""
    count, size = profiles.shape
    widths = np.full(count, np.nan)
    centres = np.full(count, np.nan)
    if count == 0:
        return widths, centres
    third = max(size // 3, 1)
    background = np.minimum(
        np.median(profiles[:, :third], axis=1), np.median(profiles[:, -third:], axis=1)
    )
    # where beads run together (a corner, a crossing) a profile's ends are glue too: its
    # background is never taken above the part's own along this segment
    background = np.minimum(background, float(np.median(background)) + GLUE_CONTRAST_MIN / 3)
    contrast = profiles - background[:, None]
    peaks = contrast.max(axis=1)
    with_glue = peaks > GLUE_CONTRAST_MIN
    if not with_glue.any():
        return widths, centres
    level = float(np.percentile(peaks[with_glue], 75))  # the bead's full contrast here
    lit = np.maximum(np.median(luma[:, :third], axis=1), np.median(luma[:, -third:], axis=1))
    levels = np.maximum(level, GLUE_CONTRAST_PER_LUMA * lit)
    margin = max(1, round(1.0 / PROFILE_STEP_MM))  # 1 mm beyond the half-level edges: blur
    middle = size // 2
    for i in np.flatnonzero(with_glue):
        full = float(levels[i])
        runs = _runs(contrast[i] > full / 2.0)
        if not runs:
            continue
        a, b = min(
            runs,
            key=lambda r: (
                0 if r[0] <= middle < r[1] else min(abs(r[0] - middle), abs(r[1] - 1 - middle))
            ),
        )
        lo, hi = max(a - margin, 0), min(b + margin, size)
        part = contrast[i, lo:hi].astype(np.float64)
        widths[i] = float(part.sum()) * PROFILE_STEP_MM / full
        weights = np.clip(part, 0.0, None)
        centres[i] = float((weights * offsets[lo:hi]).sum() / max(weights.sum(), 1e-9))
    return widths, centres


# --- judging -----------------------------------------------------------------------------


def _running_median(values: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    if len(values) < window:
        return np.full(len(values), float(np.median(values))) if len(values) else values
    half = window // 2
    padded = np.pad(values, (half, window - 1 - half), mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, window)
    return np.asarray(np.median(windows, axis=1), dtype=np.float64)


def _judge(
    segment: BeadSegment,
    stations: _Stations,
    widths: NDArray[np.float64],
    centres: NDArray[np.float64],
    seen: NDArray[np.bool_],
    tolerances: BeadTolerances,
) -> SegmentBead:
    name = f"segment {segment.index}"
    expected = segment.expected_width_mm
    present = seen & np.isfinite(widths) & (widths >= PRESENT_FRACTION * expected)
    step = stations.length / max(len(stations.along), 1)
    problems: list[str] = []

    gaps: list[tuple[float, float]] = []
    for a, b in _runs(seen & ~present):
        gaps.append((max(a * step, 0.0), min(b * step, stations.length)))
    longest = max((b - a for a, b in gaps), default=0.0)

    measured = present & ~stations.corner
    w = widths[measured]
    off = np.abs(centres[measured])
    width_mean = float(w.mean()) if len(w) else None
    offset_mean = float(off.mean()) if len(off) else None
    offset_max: float | None = None
    if len(off):
        run = min(OFFSET_RUN, len(off))
        held = np.lib.stride_tricks.sliding_window_view(off, run).min(axis=1)
        offset_max = float(held.max())

    if not seen.any():
        problems.append(
            f"{name}: its {stations.length:.1f} mm path is outside the camera's view; "
            "check the camera's calibration and the part's place"
        )
    elif not present.any():
        problems.append(
            f"{name}: no bead found along its {stations.length:.1f} mm "
            f"(a gap of at most {tolerances.max_gap_mm:.1f} mm is allowed); check the glue "
            "supply, the valve and the nozzle, and that the part did not move"
        )
    else:
        if longest > tolerances.max_gap_mm:
            start, end = max(gaps, key=lambda g: g[1] - g[0])
            others = len([g for g in gaps if g[1] - g[0] > tolerances.max_gap_mm]) - 1
            more = f" (and {others} more)" if others > 0 else ""
            problems.append(
                f"{name}: a gap of {longest:.1f} mm without bead (at most "
                f"{tolerances.max_gap_mm:.1f} mm), {start:.1f} to {end:.1f} mm from its "
                f"start{more}; check that the valve opens on time and the nozzle is clear"
            )
        tol = tolerances.width_tolerance_percent / 100.0
        low, high = expected * (1.0 - tol), expected * (1.0 + tol)
        band = f"expected {expected:.1f} mm ± {tolerances.width_tolerance_percent:g} %"
        if width_mean is not None and not low <= width_mean <= high:
            hint = (
                "check the nozzle for a blockage and the glue flow"
                if width_mean < low
                else "check the flow setpoint and the spray speed"
            )
            problems.append(
                f"{name}: the bead is {width_mean:.1f} mm wide on average, {band}; {hint}"
            )
        elif len(w):
            window = max(1, round(WIDTH_STRETCH_MM / max(step, 1e-9) / 2))
            smooth = _running_median(w, window)
            out = (smooth < low) | (smooth > high)
            along = stations.along[measured]
            for a, b in _runs(out):
                if along[b - 1] - along[a] + step > WIDTH_STRETCH_MM:
                    problems.append(
                        f"{name}: the bead is {float(np.median(w[a:b])):.1f} mm wide over "
                        f"{along[b - 1] - along[a] + step:.0f} mm from {along[a]:.0f} mm, "
                        f"{band}; check the nozzle and the glue flow"
                    )
                    break
        if offset_max is not None and offset_max > tolerances.max_offset_mm:
            problems.append(
                f"{name}: the bead lies {offset_max:.1f} mm off its planned path (at most "
                f"{tolerances.max_offset_mm:.1f} mm); check that the part did not move "
                "after it was located and the camera's calibration"
            )

    trace = np.column_stack(
        [
            stations.points + np.nan_to_num(centres)[:, None] * stations.normals,
            widths,
            np.where(~seen, -1.0, present.astype(np.float64)),
        ]
    )
    return SegmentBead(
        index=segment.index,
        workpiece_id=segment.workpiece_id,
        length_mm=stations.length,
        width_mean_mm=width_mean,
        width_min_mm=float(w.min()) if len(w) else None,
        width_max_mm=float(w.max()) if len(w) else None,
        gaps_mm=gaps,
        longest_gap_mm=longest,
        offset_mean_mm=offset_mean,
        offset_max_mm=offset_max,
        problems=problems,
        trace=trace,
    )


def inspect_bead(
    frame: np.ndarray,
    segments: Sequence[BeadSegment],
    calibration: PlaneCalibration,
    tolerances: BeadTolerances,
) -> list[SegmentBead]:
    """Find and judge the bead along each segment of an undistorted BGR frame (see module)."""
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"inspect_bead needs a BGR frame (H×W×3), got shape {frame.shape}")
    image = frame if frame.dtype == np.uint8 else np.clip(frame, 0, 255).astype(np.uint8)
    findings = []
    for segment in segments:
        path = np.asarray(segment.path_mm, dtype=np.float64).reshape(-1, 2)
        expected = float(segment.expected_width_mm)
        half = max(2.0 * expected, expected / 2.0 + 4.0 * tolerances.max_offset_mm)
        count = 2 * math.ceil(half / PROFILE_STEP_MM) + 1
        offsets = (np.arange(count, dtype=np.float64) - count // 2) * PROFILE_STEP_MM
        stations = _stations(path, corner_zone_mm=expected + STEP_MM)
        others = [s for s in segments if s is not segment]
        stations = dataclasses.replace(
            stations, corner=stations.corner | _crowded(stations, segment, others)
        )
        if len(stations.along):
            profiles, luma, seen = _profiles(image, stations, offsets, calibration)
            widths, centres = _measure(profiles, luma, offsets)
        else:
            seen = np.zeros(0, dtype=bool)
            widths = centres = np.zeros(0)
        findings.append(_judge(segment, stations, widths, centres, seen, tolerances))
    return findings


# --- the annotated image -----------------------------------------------------------------

_GOOD = (60, 200, 60)
_BAD = (40, 40, 230)
_PLAN = (230, 160, 40)


def annotate_bead(
    frame: np.ndarray,
    segments: Sequence[BeadSegment],
    findings: Sequence[SegmentBead],
    calibration: PlaneCalibration,
    reasons: Sequence[str] | None = None,
) -> np.ndarray:
    """The frame with the plan (blue), the bead found (its centre, green on a good segment,
    red on a defective one), gaps (red along the plan) and offsets beyond tolerance (red
    ticks from the plan to the bead), and the verdict with the first reasons.

    `reasons` are the part's own (its path, its glue, its position and its bead): the
    stamp says the part's verdict, so a clean bead on a part judged defective on its
    glue volume is stamped DEFECTIVE. Without them the stamp says the bead's findings."""
    out = np.ascontiguousarray(frame.copy())
    shift = 4
    scale = 1 << shift

    def px(points_mm: NDArray[np.float64]) -> NDArray[np.int32]:
        pixels = calibration.to_pixels(np.asarray(points_mm, dtype=np.float64).reshape(-1, 2))
        return np.rint(pixels * scale).astype(np.int32)

    by_index = {f.index: f for f in findings}
    for segment in segments:
        path = np.asarray(segment.path_mm, dtype=np.float64).reshape(-1, 2)
        if len(path) >= 2:
            cv2.polylines(out, [px(path)], False, _PLAN, 1, cv2.LINE_AA, shift)
        finding = by_index.get(segment.index)
        if finding is None or finding.trace is None or not len(finding.trace):
            continue
        colour = _GOOD if not finding.problems else _BAD
        trace = finding.trace
        found = trace[:, 3] > 0
        for a, b in _runs(found):
            cv2.polylines(out, [px(trace[a:b, :2])], False, colour, 2, cv2.LINE_AA, shift)
        stations = _stations(path, corner_zone_mm=0.0)
        for start, end in finding.gaps_mm:
            along = stations.along
            pick = (along >= start - 1e-6) & (along <= end + 1e-6)
            if pick.any():
                cv2.polylines(out, [px(stations.points[pick])], False, _BAD, 5, cv2.LINE_AA, shift)
        if finding.offset_max_mm is not None and any(
            "off its planned" in p for p in finding.problems
        ):
            for k in np.flatnonzero(found)[::10]:
                a, b = px(np.vstack([stations.points[k], trace[k, :2]])).tolist()
                cv2.line(out, (a[0], a[1]), (b[0], b[1]), _BAD, 2, cv2.LINE_AA, shift)
        anchor = px(path[:1])[0] // scale
        cv2.putText(
            out, str(segment.index), (int(anchor[0]) + 6, int(anchor[1]) - 6),
            cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA,
        )  # fmt: skip
    problems = list(reasons) if reasons is not None else [p for f in findings for p in f.problems]
    verdict = "GOOD" if not problems else f"DEFECTIVE ({len(problems)})"
    cv2.putText(out, verdict, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.4, (0, 0, 0), 6, cv2.LINE_AA)
    cv2.putText(
        out, verdict, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.4,
        _GOOD if not problems else _BAD, 3, cv2.LINE_AA,
    )  # fmt: skip
    for row, text in enumerate(problems[:4]):
        y = 90 + 30 * row
        cv2.putText(
            out, text[:110], (20, y), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 4, cv2.LINE_AA
        )
        cv2.putText(
            out, text[:110], (20, y), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA
        )
    return out

"""Trajectory precision: how far the robot's sampled positions lay from the planned line.

Each pose sample is tagged with the spray segment the robot was drawing; its
deviation is the shortest distance from the sample to that segment's planned
polyline (not to the nearest waypoint: a sample between two waypoints on the
line is exact). Per segment the mean and max; run-wide mean, p95 and max.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from server.quality.model import PlannedSegment, PoseSample


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Shortest distance (mm) from each of `points` (M, 2) to the polyline (N, 2)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    line = np.asarray(polyline, dtype=np.float64).reshape(-1, 2)
    if len(line) == 1:
        return np.linalg.norm(pts - line[0], axis=1)
    a, b = line[:-1], line[1:]
    ab = b - a
    length2 = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    ap = pts[:, None, :] - a[None, :, :]
    t = np.clip(np.sum(ap * ab[None], axis=2) / length2[None], 0.0, 1.0)
    nearest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(pts[:, None, :] - nearest, axis=2), axis=1)


def _round(value: float | None) -> float | None:
    return None if value is None else round(float(value), 3)


def trajectory_precision(
    samples: Sequence[PoseSample], segments: Sequence[PlannedSegment]
) -> dict[str, Any]:
    """Per segment {index, samples, mean_mm, max_mm}; run-wide mean_mm, p95_mm, max_mm.

    A segment without samples has None figures (too short for the interval);
    a run without any has None run-wide.
    """
    by_index = {s.index: s for s in segments}
    all_distances: list[np.ndarray] = []
    per_segment = []
    for segment in segments:
        mine = [(p.x, p.y) for p in samples if p.segment == segment.index]
        mean: float | None = None
        peak: float | None = None
        if mine:
            d = distance_to_polyline(np.asarray(mine), by_index[segment.index].path_mm)
            all_distances.append(d)
            mean, peak = float(d.mean()), float(d.max())
        per_segment.append(
            {
                "index": segment.index,
                "samples": len(mine),
                "mean_mm": _round(mean),
                "max_mm": _round(peak),
            }
        )
    if all_distances:
        d = np.concatenate(all_distances)
        run = {
            "samples": int(d.size),
            "mean_mm": _round(d.mean()),
            "p95_mm": _round(np.percentile(d, 95)),
            "max_mm": _round(d.max()),
        }
    else:
        run = {"samples": 0, "mean_mm": None, "p95_mm": None, "max_mm": None}
    return {**run, "segments": per_segment}

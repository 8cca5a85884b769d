"""The glue bead the simulated cell actually dispensed, for the simulated camera to render.

The bead is laid down where the nozzle was while glue left it: the robot simulator's executed
path (timed segments) says where the nozzle was when, the glue simulator's history (valve and
flow target per change, replayed through its own flow model) says how much glue left it then.
At each instant the deposit is at the nozzle's x, y with the width `expected_bead_width_mm`
gives for that flow over the nozzle's commanded speed. Both are in simulated time, so a cell
run faster (`simulation_speed_factor`) lays the same bead. Glue leaving while the arm stands
still (a few milliseconds between moves) is not drawn.

A part shifted on the table carries the bead already on it: a deposit made before a shift
moves with it, one made after lands where the nozzle was. Nothing here knows what the
inspection will find: it draws what was dispensed, no more.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from server.drivers.sim.glue_flow import flow_at
from server.vision.bead import expected_bead_width_mm

if TYPE_CHECKING:
    from server.drivers.sim.robot_sim import PathSegment

# An amber bead (a hot-melt or PU adhesive) on aluminium: clearly coloured, and brighter in
# grey than the part/table threshold (grey ~178 against the part's ~193), so a bead inside a
# part never breaks its outline; one laid on the edge adds its outer half to the silhouette.
BEAD_BGR = (80.0, 170.0, 230.0)
DEPOSIT_STEP_MM = 0.25  # spacing of the deposits along the path (the table image's pixel)
MIN_WIDTH_MM = 0.05  # thinner than this: nothing visible
SUPERSAMPLE = 4  # the bead is drawn this much finer than the table image


@dataclass(frozen=True, eq=False)
class BeadLayer:
    """The dispensed bead as strokes of (x mm, y mm, width mm) rows; `key` names its content
    so the render cache tells one bead from another."""

    strokes: tuple[NDArray[np.float64], ...]
    key: str

    @classmethod
    def of(cls, strokes: Sequence[NDArray[np.float64]]) -> BeadLayer:
        kept = tuple(np.asarray(s, dtype=np.float64).reshape(-1, 3) for s in strokes if len(s))
        digest = hashlib.blake2b(digest_size=16)
        for stroke in kept:
            digest.update(np.ascontiguousarray(stroke).tobytes())
            digest.update(b"|")
        return cls(kept, digest.hexdigest())

    def __bool__(self) -> bool:
        return bool(self.strokes)


Shift = tuple[float, float, float]  # (time.time(), dx mm, dy mm)


def deposit_strokes(
    path: Sequence[PathSegment],
    history: Sequence[tuple[float, bool, float]],
    speed_factor: float,
    *,
    since: float = -math.inf,
    shifts: Sequence[Shift] = (),
) -> BeadLayer:
    """The bead laid along `path` by the glue `history` (see the module), from `since` on."""
    segments = [s for s in path if s.t_end > since and s.speed > 0]
    samples: list[tuple[NDArray[np.float64], NDArray[np.float64], float]] = []
    for segment in segments:
        start = np.array(segment.start[:2], dtype=np.float64)
        end = np.array(segment.end[:2], dtype=np.float64)
        length = float(np.hypot(*(end - start)))
        if length < DEPOSIT_STEP_MM:
            continue
        count = math.ceil(length / DEPOSIT_STEP_MM) + 1
        fraction = np.linspace(0.0, 1.0, count)
        times = segment.t_start + (segment.t_end - segment.t_start) * fraction
        points = start + fraction[:, None] * (end - start)
        samples.append((times, points, segment.speed))
    if not samples:
        return BeadLayer.of([])
    all_times = np.concatenate([t for t, _, _ in samples])
    order = np.argsort(all_times, kind="stable")
    flows_sorted = np.asarray(flow_at(history, all_times[order].tolist(), speed_factor))
    flows = np.empty_like(flows_sorted)
    flows[order] = flows_sorted
    strokes: list[NDArray[np.float64]] = []
    offset = 0
    for times, points, speed in samples:
        flow = flows[offset : offset + len(times)]
        offset += len(times)
        widths = np.array([expected_bead_width_mm(f, speed) for f in flow])
        moved = points.copy()
        for at, dx, dy in shifts:
            moved[times < at] += (dx, dy)
        laid = (widths >= MIN_WIDTH_MM) & (times >= since)
        padded = np.concatenate([[False], laid, [False]]).astype(np.int8)
        edges = np.flatnonzero(np.diff(padded))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            strokes.append(np.column_stack([moved[a:b], widths[a:b]]))
    return BeadLayer.of(strokes)


BeadSource = Callable[[float, Sequence[Shift]], BeadLayer]


def dispensed_by(robot: Any, glue: Any) -> BeadSource:
    """What the in-process simulators dispensed, as the simulated camera asks for it:
    `source(since, shifts)` is the bead laid from `since` (time.time()) on.

    `robot` is a `RobotSimulator` (its `path_snapshot`), `glue` a `GlueSimulator` (its
    `history` and speed factor); both only copied here, so a render thread may call it.
    """

    def source(since: float, shifts: Sequence[Shift]) -> BeadLayer:
        return deposit_strokes(
            robot.path_snapshot(since),
            list(glue.history),
            glue.speed_factor,
            since=since,
            shifts=shifts,
        )

    return source


def bead_coverage(
    layer: BeadLayer,
    to_px: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    res_mm: float,
    shape: tuple[int, int],
    pad: int,
) -> tuple[int, int, NDArray[np.float32]] | None:
    """The bead's area coverage (0..1) on the table image: (row0, col0, local float image).

    Each deposit is a disc of its width; their union (spaced a table pixel apart) is the
    bead with its round ends, its coverage exact to about a sixteenth of a table pixel.
    None outside the image.
    """
    rows, cols = shape
    everything = np.vstack([to_px(s[:, :2]) for s in layer.strokes])
    reach = max(float(s[:, 2].max()) for s in layer.strokes) / res_mm / 2.0 + pad
    c0 = max(math.floor(everything[:, 0].min() - reach), 0)
    r0 = max(math.floor(everything[:, 1].min() - reach), 0)
    c1 = min(math.ceil(everything[:, 0].max() + reach) + 1, cols)
    r1 = min(math.ceil(everything[:, 1].max() + reach) + 1, rows)
    if c1 <= c0 or r1 <= r0:
        return None
    # Binary discs on a 4× finer grid, then area-averaged: an exact union (anti-aliased discs
    # drawn over each other would add up their soft edges and widen the bead).
    fine = SUPERSAMPLE
    mask = np.zeros(((r1 - r0) * fine, (c1 - c0) * fine), dtype=np.uint8)
    shift = 2
    scale = float(fine << shift)
    for stroke in layer.strokes:
        # a table pixel's centre is at its index; the fine grid's pixel centres sit at
        # (index + 0.5) / fine - 0.5 of it
        centres = np.rint(((to_px(stroke[:, :2]) - (c0, r0) + 0.5) * fine - 0.5) * (1 << shift))
        radii = np.rint(stroke[:, 2] / res_mm / 2.0 * scale).astype(np.int64)
        for (x, y), r in zip(centres.astype(np.int64).tolist(), radii.tolist(), strict=True):
            cv2.circle(mask, (x, y), r, 255, -1, cv2.LINE_8, shift)
    coverage = cv2.resize(mask, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA)
    return r0, c0, coverage.astype(np.float32) / 255.0

"""What the run's sampler collects and what the plan promised: plain data, no I/O.

Kept apart from the maths (precision.py, dispensing.py) so those are pure
functions of lists a unit test can write by hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, slots=True)
class PlannedSegment:
    """One spray polyline of the plan: the run of consecutive spray waypoints.

    `path_mm` starts where the valve opens (the waypoint before the first spray
    one: the descent onto the line's start), so it is the whole line the robot
    draws with glue flowing. 1-based `index`, in plan order.
    """

    index: int
    workpiece_id: str
    path_mm: np.ndarray  # (N, 2) x, y mm, robot/table frame
    speed_mm_s: float
    flow_ml_min: float

    @property
    def length_mm(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.path_mm, axis=0), axis=1)))

    @property
    def spray_time_s(self) -> float:
        """The spraying time the plan needs: length / speed."""
        return self.length_mm / self.speed_mm_s

    @property
    def expected_ml(self) -> float:
        """Glue the plan needs: setpoint × length / speed."""
        return self.flow_ml_min / 60.0 * self.spray_time_s


@dataclass(frozen=True, slots=True)
class PoseSample:
    """The robot's position read while it drew `segment`."""

    at: float  # monotonic s
    x: float
    y: float
    segment: int


@dataclass(frozen=True, slots=True)
class FlowSample:
    """One status reading of the dispenser (as its driver's monitor took it)."""

    at: float  # monotonic s
    flow_ml_min: float
    setpoint_ml_min: float
    valve_open: bool
    total_ml: float | None = None  # the dispenser's totaliser (None: it keeps none)


@dataclass(slots=True)
class SprayWindow:
    """From the valve's open answered to its close answered, on one segment."""

    segment: int
    opened_at: float  # monotonic s
    closed_at: float | None = None


@dataclass(slots=True)
class RunSamples:
    """Everything the sampler collected during one run's path."""

    poses: list[PoseSample] = field(default_factory=list)
    flows: list[FlowSample] = field(default_factory=list)
    windows: list[SprayWindow] = field(default_factory=list)

    def as_counts(self) -> dict[str, Any]:
        return {"poses": len(self.poses), "flows": len(self.flows), "windows": len(self.windows)}


def spray_segments(waypoints: list[Any]) -> tuple[list[PlannedSegment], dict[int, int]]:
    """The plan's spray segments, and which segment each spray waypoint (0-based) draws.

    `waypoints` are trajectory Waypoints (pose, spray, speed, workpiece, flow_rate_ml_min).
    """
    segments: list[PlannedSegment] = []
    owner: dict[int, int] = {}
    index = 0
    while index < len(waypoints):
        if not waypoints[index].spray:
            index += 1
            continue
        start = index
        while index < len(waypoints) and waypoints[index].spray:
            owner[index] = len(segments) + 1
            index += 1
        first = waypoints[start - 1] if start > 0 else waypoints[start]
        points = [(first.pose.x, first.pose.y)]
        points += [(w.pose.x, w.pose.y) for w in waypoints[start:index]]
        head = waypoints[start]
        segments.append(
            PlannedSegment(
                len(segments) + 1,
                head.workpiece,
                np.asarray(points, dtype=np.float64),
                float(head.speed),
                float(head.flow_rate_ml_min),
            )
        )
    return segments, owner

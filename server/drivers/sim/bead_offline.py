"""A spray run laid down offline: the robot's timed path and the glue's history, no servers.

For the benchmark and the tests of the bead inspection: the same records the simulators keep
during a real run (`PathSegment`s, the glue history), built from the planned polylines at a
spray speed and flow, with the defects the cell's faults cause: a partly clogged nozzle, a
valve that opens late, a valve closed over a stretch (a gap), a part shifted part-way. The
bead is then `camera_bead.deposit_strokes` of them, rendered by the simulated camera.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from server.drivers.base import Pose
from server.drivers.sim.camera_bead import BeadLayer, Shift, deposit_strokes
from server.drivers.sim.robot_sim import PathSegment

Z_MM = 20.0


@dataclass(frozen=True)
class Defects:
    """What goes wrong in the run (all off by default)."""

    clog_fraction: float = 1.0  # flow as a fraction of its setpoint, from clog_from_s on
    clog_from_s: float = 0.0
    valve_delay_s: float = 0.0  # each opening this late after its command
    gap: tuple[int, float, float] | None = None  # (polyline 0-based, from mm, length mm)
    shift: tuple[float, float, float] | None = None  # (dx mm, dy mm, at this fraction of the run)


def lay_bead(
    polylines: Sequence[NDArray[np.float64]],
    speed_mm_s: float,
    flow_ml_min: float,
    defects: Defects = Defects(),
    *,
    t0: float = 1_000.0,
) -> BeadLayer:
    """The bead a run along `polylines` dispenses (valve opened at each polyline's start and
    closed at its end, as the trajectory operation does), with `defects`."""
    path: list[PathSegment] = []
    history: list[tuple[float, bool, float]] = [(t0 - 1.0, False, flow_ml_min)]
    t = t0
    for number, line in enumerate(polylines):
        pts = np.asarray(line, dtype=np.float64)
        opened = t + defects.valve_delay_s
        history.append((opened, True, flow_ml_min))
        run_start = t
        for a, b in itertools.pairwise(pts):
            duration = float(np.hypot(*(b - a))) / speed_mm_s
            start, end = Pose(float(a[0]), float(a[1]), Z_MM), Pose(float(b[0]), float(b[1]), Z_MM)
            path.append(PathSegment("moveL", start, end, speed_mm_s, False, t, t + duration))
            t += duration
        history.append((t, False, flow_ml_min))
        if defects.gap is not None and defects.gap[0] == number:
            _, start_mm, length_mm = defects.gap
            closes = run_start + start_mm / speed_mm_s
            history.append((closes, False, flow_ml_min))
            history.append((closes + length_mm / speed_mm_s, True, flow_ml_min))
        t += 0.5  # lift, travel, descend
    history.sort(key=lambda h: h[0])
    if defects.clog_fraction != 1.0:
        at = t0 + defects.clog_from_s
        before = [h for h in history if h[0] < at]
        state = before[-1][1] if before else False
        clogged = flow_ml_min * defects.clog_fraction
        history = [*before, (at, state, clogged)] + [
            (when, is_open, clogged) for when, is_open, _ in history if when >= at
        ]
    shifts: list[Shift] = []
    if defects.shift is not None:
        dx, dy, fraction = defects.shift
        shifts.append((t0 + fraction * (t - t0), dx, dy))
    return deposit_strokes(path, history, 1.0, shifts=shifts)

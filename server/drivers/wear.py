"""Wear counters a driver keeps in its `health.details`: what it already sees, counted.

Each driver adds to monotonic totals since it was made (valve cycles, open seconds and
millilitres dispensed; robot travel and motion seconds; camera frames). They are
never reset: the cell's wear meter (server/core/worker/care.py) reads them and
adds what grew since its last read to the totals the journal keeps across
restarts, so a driver knows nothing of persistence and costs one addition per
exchange.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

# The counter names, as health.details keys (the wear meter reads these).
VALVE_CYCLES = "wear_valve_cycles"
VALVE_OPEN_S = "wear_valve_open_s"
GLUE_ML = "wear_glue_ml"
TRAVEL_M = "wear_travel_m"
MOTION_S = "wear_motion_s"
FRAMES = "wear_frames"

COUNTERS = (VALVE_CYCLES, VALVE_OPEN_S, GLUE_ML, TRAVEL_M, MOTION_S, FRAMES)


def add(details: dict[str, Any], counter: str, amount: float) -> None:
    """Add `amount` (never negative) to `counter` in `details`."""
    if amount > 0:
        details[counter] = details.get(counter, 0) + amount


def travel_m(before: Sequence[float] | None, after: Sequence[float]) -> float:
    """The straight distance (m) between two tool positions in mm, 0 without a before."""
    if before is None or len(before) < 3:
        return 0.0
    return math.dist(before[:3], after[:3]) / 1000.0


def glue_held(details: dict[str, Any], now: float, flow_now: float | None = None) -> None:
    """A dispenser's open time and glue dispensed since its last status read (`status_at`),
    while that read saw the valve open: at the mean of the flow it measured and `flow_now`
    (this read's, 0 with the valve closed), or at its own flow when there is no reading
    now (the driver's own close, read back).

    Why the mean and not the earlier reading held: a speed-following flow drops as the
    arm slows at each waypoint, and a read that comes late (a loaded machine) held the
    flow of a moving arm over a standing one, or the reverse; the mean of the two ends
    of the interval errs less on a flow that changed within it.
    """
    held = now - details.get("status_at", now)
    if details.get("valve_open") and held > 0:
        before = float(details.get("flow_ml_min") or 0.0)
        flow = before if flow_now is None else (before + flow_now) / 2.0
        add(details, VALVE_OPEN_S, held)
        add(details, GLUE_ML, flow / 60.0 * held)

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

from server.drivers.glue_registers import dispensed_since

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


def valve_open_held(details: dict[str, Any], now: float) -> None:
    """A dispenser's open time since its last status read (`status_at`), while that read
    saw the valve open."""
    held = now - details.get("status_at", now)
    if details.get("valve_open") and held > 0:
        add(details, VALVE_OPEN_S, held)


def glue_counted(details: dict[str, Any], total_ml: float | None) -> None:
    """Glue dispensed since the last status read, by the dispenser's own totaliser
    (`dispensed_ml` in `details` is the count that read saw). The device counts every
    drop whenever it is read, so the figure does not depend on when the polls come."""
    before = details.get("dispensed_ml")
    if total_ml is not None and before is not None:
        add(details, GLUE_ML, dispensed_since(float(before), total_ml))

"""Dispensing consistency: the flow while the valve was open, against its setpoint.

Readings count when the dispenser itself reported the valve open inside a
spray window (the run's own open and close, answered), past the opening
transient (`OPENING_TRANSIENT_S`: the flow settles within a few of the
dispenser's time constants, as the glue driver's own deviation check allows).

- coefficient of variation (%) = 100 × standard deviation / mean of those readings;
- out of tolerance (s): each reading stands for the time until the next one (or
  the window's end); the sum over readings further than the tolerance (%) from
  the setpoint;
- glue dispensed (ml) = the dispenser's totaliser at its first reading after
  the last close against its last reading before the first open, both showing
  the valve closed (`glue_from` "totaliser"): the device counts every drop
  however far apart the polls are, so neither a stretched nor a late poll
  changes the figure. Without such a pair (a dispenser that keeps no count, a
  poll lost) it is ∫ flow dt over the spray windows, each reading held until
  the next (`glue_from` "flow readings");
- expected (ml) = Σ setpoint × length / speed over the plan's spray segments.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from server.drivers.glue_registers import dispensed_since
from server.quality.model import FlowSample, PlannedSegment, SprayWindow

OPENING_TRANSIENT_S = 0.15


def _within(flows: Sequence[FlowSample], window: SprayWindow, end: float) -> list[FlowSample]:
    return [f for f in flows if window.opened_at <= f.at <= end and f.valve_open]


def counted_ml(flows: Sequence[FlowSample], windows: Sequence[SprayWindow]) -> float | None:
    """The totaliser's growth over the spray windows (module docstring); None without a
    count read with the valve closed before the first open and after the last close."""
    if not windows or windows[-1].closed_at is None:
        return None
    first_open, last_close = windows[0].opened_at, windows[-1].closed_at
    counts = [(f.at, f.total_ml) for f in flows if f.total_ml is not None and not f.valve_open]
    before = [total for at, total in counts if at <= first_open]
    after = [total for at, total in counts if at >= last_close]
    return dispensed_since(before[-1], after[0]) if before and after else None


def dispensing_consistency(
    flows: Sequence[FlowSample],
    windows: Sequence[SprayWindow],
    segments: Sequence[PlannedSegment],
    tolerance_percent: float,
) -> dict[str, Any]:
    """The figures of the module docstring; None where no reading fell in a window."""
    ordered = sorted(flows, key=lambda f: f.at)
    judged: list[FlowSample] = []
    out_of_tolerance_s = 0.0
    glue_ml = 0.0
    for window in windows:
        end = window.closed_at if window.closed_at is not None else window.opened_at
        inside = _within(ordered, window, end)
        for i, reading in enumerate(inside):
            until = inside[i + 1].at if i + 1 < len(inside) else end
            held = max(0.0, until - reading.at)
            glue_ml += reading.flow_ml_min / 60.0 * held
            if i == 0:  # from the open to the first reading: no reading yet, held back
                glue_ml += reading.flow_ml_min / 60.0 * max(0.0, reading.at - window.opened_at)
            if reading.at - window.opened_at < OPENING_TRANSIENT_S or reading.setpoint_ml_min <= 0:
                continue
            judged.append(reading)
            off = abs(reading.flow_ml_min - reading.setpoint_ml_min) / reading.setpoint_ml_min
            if off * 100.0 > tolerance_percent:
                out_of_tolerance_s += held
    counted = counted_ml(ordered, windows)
    if counted is not None:
        glue_ml = counted
    expected_ml = sum(s.expected_ml for s in segments)
    values = np.asarray([f.flow_ml_min for f in judged], dtype=np.float64)
    cv = None
    if values.size >= 2 and values.mean() > 0:
        cv = round(float(values.std(ddof=1) / values.mean() * 100.0), 3)
    setpoints = [f.setpoint_ml_min for f in judged]
    return {
        "readings": int(values.size),
        "flow_mean_ml_min": round(float(values.mean()), 3) if values.size else None,
        "setpoint_ml_min": round(float(np.mean(setpoints)), 3) if setpoints else None,
        "cv_percent": cv,
        "out_of_tolerance_s": round(out_of_tolerance_s, 3),
        "tolerance_percent": tolerance_percent,
        "spraying_s": round(sum((w.closed_at or w.opened_at) - w.opened_at for w in windows), 3),
        "glue_ml": round(glue_ml, 4) if windows else None,
        "glue_from": ("totaliser" if counted is not None else "flow readings") if windows else None,
        "expected_ml": round(expected_ml, 4),
        "glue_ratio_percent": (
            round(glue_ml / expected_ml * 100.0, 2) if windows and expected_ml > 0 else None
        ),
    }

"""Key performance indicators of the cell, computed from rows of the journal.

Why pure functions: the journal only stores what happened (transitions,
operations, errors, recovery attempts). Turning those rows into figures is
plain arithmetic, kept here apart from SQLite and HTTP so that every formula
can be checked against a journal written out by hand, and so the API, a
report script and a test all compute a KPI the same way. Nothing is rounded:
the caller decides how a figure is shown.

Rows are plain mappings, as the journal hands them over (times are Unix
seconds):

* transitions: ``time, old_state, new_state, event, event_id, time_in_old_state``
* operations: ``run_id, kind, started_at, ended_at, outcome, workpieces, result``
  (``result`` decoded from the journal's JSON: a mapping, or None)
* errors: ``time, code, component, classification, event_id``
* recoveries: ``time, error_code, attempt, succeeded``

The journal records only changes of state, so the intervals that the
transition rows describe do not overlap. Time the server was down is covered
by no row and counts as neither available nor unavailable: it is simply not
in ``A``. The state the server was in when it stopped has no closing row, so
that last interval before a shutdown is not counted either.

Formulas (the same text as docs/kpis.md)::

    W     = [start, end), half-open: a row stamped exactly `end` belongs to the next window
    hours = (end - start) / 3600
    T(s)  = seconds in state s inside W: each transition row is the interval
            [time - time_in_old_state, time] in old_state, and [current_since, now]
            is in current_state; every interval is clipped to W before it is summed
    A     = sum of T(s) over every state (available time: the server was up)
    X     = T(EXECUTING_TRAJECTORY)     R = T(ERROR)
    ENDED = operations whose ended_at is in W (any outcome); running ones are ignored
    DONE  = ENDED with outcome "completed"
    ENDED_TRAJ, DONE_TRAJ = the same, of kind "trajectory"
    PARTS = ENDED_TRAJ, one part each, judged by part_verdict(outcome, result, error)
            (server/quality/part_verdict.py), as every other path judges it
    GOOD, DEFECTIVE, NOT_INSPECTED = PARTS with verdict "good", "defective",
            "not_inspected" (a run that did not complete left a defective part)
    INSPECTED = PARTS whose result holds an inspection (result["inspection"]
            with verdict "good" or "defective")
    p95(v) = the nearest-rank 95th percentile: v sorted, its ceil(0.95 * |v|)-th value

    operations_completed_per_hour = |DONE| / hours
    average_execution_time_s[k]   = mean(ended_at - started_at) over DONE of kind k
    utilization                   = X / A
    error_rate_per_100_operations = 100 * |errors in W classed critical or recoverable| / |ENDED|
    failures                      = |transitions in W with new_state ERROR, old_state not ERROR|
    mtbf_s                        = (A - R) / failures
    mttr_s                        = mean(time_in_old_state) over transitions in W leaving ERROR
    error_recovery_success_rate   = |recoveries in W that succeeded| / |recoveries in W|
    time_in_state_s[s]            = T(s)
    workpieces_processed          = sum(workpieces) over DONE_TRAJ
    workpieces_failed             = sum(workpieces) over ENDED_TRAJ failed or interrupted
    oee.availability              = (A - R) / A
    oee.performance               = min(1, design_cycle_time_s * |DONE_TRAJ| / X)
    oee.quality                   = |GOOD| / (|GOOD| + |DEFECTIVE|)
    oee.oee                       = availability * performance * quality
    quality.parts_good            = |GOOD|
    quality.parts_defective       = |DEFECTIVE|
    quality.parts_not_inspected   = |NOT_INSPECTED|
    quality.trajectory_precision_mm.mean = mean(precision_mean_mm) over INSPECTED
    quality.trajectory_precision_mm.p95  = p95(precision_p95_mm over INSPECTED)
    quality.dispensing_cv_percent = mean(dispensing_cv_percent) over INSPECTED
    quality.vision_residual_mm    = mean(vision_residual_mm) over INSPECTED

    A ratio or mean over nothing (denominator 0) is null; oee.oee is null if a factor is.
    A figure an inspection did not measure (null) is left out of its mean and p95.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Final

from server.core.machine.transitions import State
from server.quality.part_verdict import (
    DEFECTIVE,
    GOOD,
    NOT_INSPECTED,
    figure_of,
    inspection_of,
    part_verdict,
)

# The operation kinds the journal records (the names of server/core/operations).
OPERATION_KINDS: Final = ("trajectory", "calibrate_robot", "calibrate_camera", "create_workpiece")
# Errors that cost production; warnings are informative and do not count.
COUNTED_CLASSIFICATIONS: Final = frozenset({"critical", "recoverable"})
# Trajectory outcomes that spoil the parts; a cancel is an operator's decision.
SPOILED_OUTCOMES: Final = frozenset({"failed", "interrupted"})

Row = Mapping[str, Any]


@dataclass(frozen=True)
class Window:
    """The half-open span ``[start, end)`` of Unix seconds a KPI report covers.

    Half-open so that consecutive windows (hour by hour, shift by shift) count
    a row stamped exactly on a boundary once, in the later window.
    """

    start: float
    end: float

    def __post_init__(self) -> None:
        # A window of no length would make every "per hour" figure a division by zero.
        if not (math.isfinite(self.start) and math.isfinite(self.end)):
            raise ValueError(f"window bounds must be finite, got [{self.start}, {self.end})")
        if self.end <= self.start:
            raise ValueError(f"window must end after it starts, got [{self.start}, {self.end})")

    @property
    def hours(self) -> float:
        """Length of the window in hours, the unit of the rates."""
        return (self.end - self.start) / 3600.0

    @property
    def seconds(self) -> float:
        """Length of the window in seconds."""
        return self.end - self.start

    def contains(self, t: float | None) -> bool:
        """Whether the instant `t` falls in ``[start, end)``; None (not yet) never does."""
        return t is not None and self.start <= t < self.end

    def overlap(self, a: float, b: float) -> float:
        """Seconds of ``[a, b]`` inside the window; 0.0 when disjoint or `b` < `a`."""
        return max(0.0, min(b, self.end) - max(a, self.start))


# The shortest default window: a shift is a settings value (at least 15 minutes), but the
# window must never be empty whatever it holds (3.55e-276 hours made every GET /kpis a 500).
MIN_SHIFT_S: Final = 60.0


def kpi_window(since: float | None, until: float | None, now: float, shift_hours: float) -> Window:
    """The window GET /kpis reports on: `until` defaults to now, `since` to a shift before it.

    A `since` still to come without an `until` is a shift that has not begun: the window is
    the shift from `since`. The shift is taken as at least MIN_SHIFT_S, and a window that
    would still be empty (bounds so large that adding the shift changes nothing) is one
    shift long from its start, so no setting and no query can make the report a 500; the
    route refuses `since` >= `until` itself with a 422.
    """
    shift_s = max(shift_hours * 3600.0, MIN_SHIFT_S) if math.isfinite(shift_hours) else MIN_SHIFT_S
    if until is not None:
        end = until
    elif since is not None and since >= now:
        end = since + shift_s
    else:
        end = now
    start = since if since is not None else end - shift_s
    if not end > start:
        end = start + max(shift_s, abs(start) * 1e-9)
    return Window(start, end)


def state_durations(
    transitions: Iterable[Row],
    window: Window,
    *,
    current_state: str,
    current_since: float,
    now: float,
) -> dict[str, float]:
    """Cumulative seconds spent in each state inside `window`.

    Each transition row closes the interval ``[time - time_in_old_state, time]``
    of its old_state; the state the cell is in now is the open interval
    ``[current_since, now]``. Every interval is clipped to the window, so a
    state entered before the window or left after it counts only its share.
    Rows stamped after the window are still read: they close intervals that
    may have begun inside it.

    Every `State` is a key (0.0 when the cell was never in it), so callers can
    index without guarding; a state name the enum does not know (an older
    journal) keeps its own key rather than vanishing from the available time.
    """
    parts: dict[str, list[float]] = {state.value: [] for state in State}
    for row in transitions:
        end = float(row["time"])
        start = end - float(row["time_in_old_state"])
        parts.setdefault(str(row["old_state"]), []).append(window.overlap(start, end))
    parts.setdefault(current_state, []).append(window.overlap(float(current_since), float(now)))
    # fsum: an 8 h shift of many short states should still add up to the second.
    return {state: math.fsum(values) for state, values in parts.items()}


def _ratio(numerator: float, denominator: float) -> float | None:
    """numerator / denominator, or None when there is nothing to divide by."""
    return numerator / denominator if denominator else None


def _mean(values: list[float]) -> float | None:
    """Arithmetic mean, or None for no values (a mean of nothing is unknown, not 0)."""
    return math.fsum(values) / len(values) if values else None


def _p95(values: list[float]) -> float | None:
    """Nearest-rank 95th percentile: a value that occurred, so a hand count checks it."""
    if not values:
        return None
    ordered = sorted(values)
    return ordered[math.ceil(0.95 * len(ordered)) - 1]


def quality_of(ended_trajectories: Iterable[Row]) -> tuple[dict[str, Any], int]:
    """The `quality` block over trajectory runs that ended in the window, and how many
    parts were judged good or defective (OEE quality's denominator).

    Each run is one part, judged by `part_verdict` (server/quality/part_verdict.py) as
    the order card, the Last part card, the CSV and the run messages judge it: a run that
    did not complete left a defective part. The figures are those of inspected parts,
    per part, so a long run weighs no more than a short one.
    """
    runs = list(ended_trajectories)
    verdicts = [
        part_verdict(str(op.get("outcome")), op.get("result"), op.get("error")).verdict
        for op in runs
    ]
    inspected = [i for op in runs if (i := inspection_of(op.get("result")))]

    def measured(name: str) -> list[float]:
        return [v for i in inspected if (v := figure_of(i, name)) is not None]

    good, defective = verdicts.count(GOOD), verdicts.count(DEFECTIVE)
    block = {
        "parts_good": good,
        "parts_defective": defective,
        "parts_not_inspected": verdicts.count(NOT_INSPECTED),
        "trajectory_precision_mm": {
            "mean": _mean(measured("precision_mean_mm")),
            "p95": _p95(measured("precision_p95_mm")),
        },
        "dispensing_cv_percent": _mean(measured("dispensing_cv_percent")),
        "vision_residual_mm": _mean(measured("vision_residual_mm")),
    }
    return block, good + defective


def compute_kpis(
    window: Window,
    transitions: Iterable[Row],
    operations: Iterable[Row],
    errors: Iterable[Row],
    recoveries: Iterable[Row],
    *,
    current_state: str,
    current_since: float,
    now: float,
    design_cycle_time_s: float,
) -> dict[str, Any]:
    """Every KPI of the module docstring for `window`, as a JSON-able dict.

    `current_state`, `current_since` and `now` describe the interval the
    journal has not closed yet (the state the cell is in). `design_cycle_time_s`
    is the time one trajectory run should take at rated speed, the yardstick of
    OEE performance. Figures with nothing to divide by are None (JSON null), so
    a quiet window never reports a made-up 0 % or 100 %.
    """
    if not (math.isfinite(design_cycle_time_s) and design_cycle_time_s > 0):
        raise ValueError(f"design_cycle_time_s must be > 0, got {design_cycle_time_s}")
    transitions = list(transitions)

    # Time.
    durations = state_durations(
        transitions, window, current_state=current_state, current_since=current_since, now=now
    )
    available = math.fsum(durations.values())
    executing = durations[State.EXECUTING_TRAJECTORY.value]
    in_error = durations[State.ERROR.value]
    up = available - in_error

    # Operations, counted in the window they ended in.
    ended = [op for op in operations if window.contains(op.get("ended_at"))]
    done = [op for op in ended if op.get("outcome") == "completed"]
    ended_traj = [op for op in ended if op.get("kind") == "trajectory"]
    done_traj = [op for op in ended_traj if op.get("outcome") == "completed"]
    spoiled_traj = [op for op in ended_traj if op.get("outcome") in SPOILED_OUTCOMES]

    # Every known kind is a key (null when none completed); an unknown kind keeps its own.
    run_times: dict[str, list[float]] = {kind: [] for kind in OPERATION_KINDS}
    for op in done:
        run_times.setdefault(str(op["kind"]), []).append(
            float(op["ended_at"]) - float(op["started_at"])
        )
    average_execution = {kind: _mean(times) for kind, times in run_times.items()}

    # Faults.
    counted_errors = [
        e
        for e in errors
        if window.contains(e.get("time")) and e.get("classification") in COUNTED_CLASSIFICATIONS
    ]
    error_state = State.ERROR.value
    failures = sum(
        1
        for t in transitions
        if window.contains(t["time"])
        and t["new_state"] == error_state
        and t["old_state"] != error_state
    )
    repairs = [
        float(t["time_in_old_state"])
        for t in transitions
        if window.contains(t["time"])
        and t["old_state"] == error_state
        and t["new_state"] != error_state
    ]
    attempts = [r for r in recoveries if window.contains(r.get("time"))]
    succeeded = sum(1 for r in attempts if r.get("succeeded"))

    # OEE.
    availability = _ratio(up, available)
    ideal = _ratio(design_cycle_time_s * len(done_traj), executing)
    performance = None if ideal is None else min(1.0, ideal)
    quality_block, judged = quality_of(ended_traj)
    quality = _ratio(quality_block["parts_good"], judged)
    oee = (
        None
        if availability is None or performance is None or quality is None
        else availability * performance * quality
    )

    return {
        "window": {"start": window.start, "end": window.end, "hours": window.hours},
        "available_time_s": available,
        "operations_ended": len(ended),
        "operations_completed": len(done),
        "operations_completed_per_hour": len(done) / window.hours,
        "average_execution_time_s": average_execution,
        "utilization": _ratio(executing, available),
        "errors_counted": len(counted_errors),
        "error_rate_per_100_operations": _ratio(100.0 * len(counted_errors), len(ended)),
        "failures": failures,
        "mtbf_s": _ratio(up, failures),
        "mttr_s": _mean(repairs),
        "recovery_attempts": len(attempts),
        "error_recovery_success_rate": _ratio(succeeded, len(attempts)),
        "time_in_state_s": durations,
        "workpieces_processed": sum(int(op.get("workpieces") or 0) for op in done_traj),
        "workpieces_failed": sum(int(op.get("workpieces") or 0) for op in spoiled_traj),
        "oee": {
            "availability": availability,
            "performance": performance,
            "quality": quality,
            "oee": oee,
        },
        "quality": quality_block,
    }

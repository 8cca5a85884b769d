"""KPI formulas against journals written out by hand.

Every expected figure is worked out in a comment from the timeline, not from
the module, so a test fails when a formula drifts from docs/kpis.md. Times are
whole minutes after T0, so every duration is an exact float and most ratios
are exact too; where a ratio is not, the comment gives the fraction and the
test compares it with that same fraction (one correctly rounded division).
"""

from __future__ import annotations

import json
import math
import re
import textwrap
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.core.machine.transitions import State
from server.views import kpis
from server.views.kpis import Window, compute_kpis, state_durations

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "kpis.md"

T0 = 1_709_532_000.0  # Monday 2024-03-04 06:00 UTC, the start of the shift
MIN = 60.0
HOUR = 3600.0
STATES = [s.value for s in State]


def at(minute: float) -> float:
    """Unix time `minute` minutes into the shift."""
    return T0 + minute * MIN


def journal(start_state: str, start_minute: float, steps: list[tuple[float, str, str]]):
    """Transition rows for a cell that entered `start_state` at `start_minute`, then
    took each (minute, new_state, event) step; returns (rows, current_state, current_since).

    Only `time_in_old_state` is derived here (minute - minute the old state was entered),
    so the timelines below read like the journal would.
    """
    rows: list[dict[str, Any]] = []
    state, since = start_state, start_minute
    for n, (minute, new_state, event) in enumerate(steps):
        rows.append(
            {
                "time": at(minute),
                "old_state": state,
                "new_state": new_state,
                "event": event,
                "event_id": f"ev-{n}",
                "time_in_old_state": (minute - since) * MIN,
            }
        )
        state, since = new_state, minute
    return rows, state, at(since)


def op(
    run_id: str,
    kind: str,
    start: float,
    end: float | None,
    outcome: str | None,
    wp: int = 0,
    inspection: dict[str, Any] | None = None,
):
    """An operations row; `inspection` goes in its result as the run record holds it."""
    result = None if inspection is None else {"workpieces": [], "inspection": inspection}
    return {
        "run_id": run_id,
        "kind": kind,
        "started_at": at(start),
        "ended_at": None if end is None else at(end),
        "outcome": outcome,
        "workpieces": wp,
        "result": result,
    }


def inspected(
    verdict: str,
    mean: float | None = None,
    p95: float | None = None,
    cv: float | None = None,
    residual: float | None = None,
    reasons: list[str] | None = None,
) -> dict[str, Any]:
    """An inspection summary as the inspection's contract writes it into a run's result."""
    return {
        "verdict": verdict,
        "reasons": reasons or [],
        "precision_mean_mm": mean,
        "precision_p95_mm": p95,
        "dispensing_cv_percent": cv,
        "glue_ml": 1.25,
        "vision_residual_mm": residual,
        "image": True,
    }


def err(minute: float, code: str, component: str, classification: str) -> dict[str, Any]:
    return {
        "time": at(minute),
        "code": code,
        "component": component,
        "classification": classification,
        "event_id": f"err-{minute}",
    }


def rec(minute: float, code: str, attempt: int, succeeded: bool) -> dict[str, Any]:
    return {"time": at(minute), "error_code": code, "attempt": attempt, "succeeded": succeeded}


# --- The 8 h shift: also the worked example of docs/kpis.md ------------------------------
#
#   min   0- 60  INITIALIZING   server started at T0
#        60- 70  IDLE
#        70- 80  CALIBRATING_ROBOT   cal-1 completed (10 min)
#        80- 90  IDLE
#        90-150  EXECUTING           run-A completed, 12 workpieces (60 min), inspected good
#       150-160  IDLE
#       160-200  EXECUTING           run-B ...
#       200-210  PAUSED              ... paused 10 min ...
#       210-240  EXECUTING           ... completed, 12 workpieces (80 min incl. the pause),
#                                    inspected defective
#       240-250  IDLE
#       250-280  EXECUTING           run-C failed (glue NOZZLE_BLOCKED, critical), 12 workpieces
#       280-290  ERROR               the one failure: a 10 min episode, reset at 290
#       290-300  IDLE
#       300-320  EXECUTING           run-D cancelled by the operator, 12 workpieces
#       320-330  IDLE
#       330-390  EXECUTING           run-E completed, 6 workpieces (60 min), inspected good
#       390-480  IDLE                still IDLE at the end of the shift (now = 480)
#
#   inspections (precision mean / p95 mm, flow CV %, vision residual mm):
#     A good 0.25 / 0.5, 2, 0.25; B defective 0.5 / 1.5, 12, 0.75; E good 0.75 / 0.75, 4, none
#   errors: 120 recoverable, 280 critical, 310 recoverable, 400 warning
#   recoveries: 120.5 ok, 280.5 failed, 282 failed, 310.5 ok

SHIFT = Window(at(0), at(480))
GAP_REASON = "segment 3: a gap of 14.2 mm without bead (at most 3.0 mm)"
DESIGN_CYCLE_S = 3600.0  # one trajectory run should take an hour

SHIFT_TRANSITIONS, SHIFT_STATE, SHIFT_SINCE = journal(
    "INITIALIZING",
    0,
    [
        (60, "IDLE", "SYSTEM_READY"),
        (70, "CALIBRATING_ROBOT", "CALIBRATE_ROBOT_REQUESTED"),
        (80, "IDLE", "OPERATION_COMPLETED"),
        (90, "EXECUTING_TRAJECTORY", "START_REQUESTED"),
        (150, "IDLE", "OPERATION_COMPLETED"),
        (160, "EXECUTING_TRAJECTORY", "START_REQUESTED"),
        (200, "PAUSED", "PAUSE_REQUESTED"),
        (210, "EXECUTING_TRAJECTORY", "RESUME_REQUESTED"),
        (240, "IDLE", "OPERATION_COMPLETED"),
        (250, "EXECUTING_TRAJECTORY", "START_REQUESTED"),
        (280, "ERROR", "OPERATION_FAILED"),
        (290, "IDLE", "RESET_REQUESTED"),
        (300, "EXECUTING_TRAJECTORY", "START_REQUESTED"),
        (320, "IDLE", "CANCEL_REQUESTED"),
        (330, "EXECUTING_TRAJECTORY", "START_REQUESTED"),
        (390, "IDLE", "OPERATION_COMPLETED"),
    ],
)
SHIFT_OPERATIONS = [
    op("cal-1", "calibrate_robot", 70, 80, "completed"),
    op("run-A", "trajectory", 90, 150, "completed", 12, inspected("good", 0.25, 0.5, 2.0, 0.25)),
    op(
        "run-B",
        "trajectory",
        160,
        240,
        "completed",
        12,
        inspected("defective", 0.5, 1.5, 12.0, 0.75, [GAP_REASON]),
    ),
    op("run-C", "trajectory", 250, 280, "failed", 12),
    op("run-D", "trajectory", 300, 320, "cancelled", 12),
    op("run-E", "trajectory", 330, 390, "completed", 6, inspected("good", 0.75, 0.75, 4.0)),
]
SHIFT_ERRORS = [
    err(120, "VISION_TIMEOUT", "camera", "recoverable"),
    err(280, "NOZZLE_BLOCKED", "glue", "critical"),
    err(310, "PRESSURE_LOW", "glue", "recoverable"),
    err(400, "GLUE_LEVEL_LOW", "glue", "warning"),
]
SHIFT_RECOVERIES = [
    rec(120.5, "VISION_TIMEOUT", 1, True),
    rec(280.5, "NOZZLE_BLOCKED", 1, False),
    rec(282, "NOZZLE_BLOCKED", 2, False),
    rec(310.5, "PRESSURE_LOW", 1, True),
]


def shift_kpis(window: Window = SHIFT, now: float = at(480)) -> dict[str, Any]:
    return compute_kpis(
        window,
        SHIFT_TRANSITIONS,
        SHIFT_OPERATIONS,
        SHIFT_ERRORS,
        SHIFT_RECOVERIES,
        current_state=SHIFT_STATE,
        current_since=SHIFT_SINCE,
        now=now,
        design_cycle_time_s=DESIGN_CYCLE_S,
    )


def test_shift_journal_is_what_the_timeline_says() -> None:
    assert len(SHIFT_TRANSITIONS) == 16
    assert SHIFT_STATE == "IDLE"
    assert (SHIFT_SINCE - T0) / MIN == 390  # IDLE since minute 390
    assert SHIFT_TRANSITIONS[10] == {
        "time": at(280),
        "old_state": "EXECUTING_TRAJECTORY",
        "new_state": "ERROR",
        "event": "OPERATION_FAILED",
        "event_id": "ev-10",
        "time_in_old_state": 1800.0,
    }


def test_shift_time_in_state() -> None:
    k = shift_kpis()
    assert k["window"] == {"start": at(0), "end": at(480), "hours": 8.0}
    assert k["time_in_state_s"] == {
        "INITIALIZING": 3600.0,  # 0-60
        "IDLE": 9000.0,  # 10+10+10+10+10+10 min between runs + 90 min open at the end = 150 min
        "CALIBRATING_ROBOT": 600.0,  # 70-80
        "CALIBRATING_CAMERA": 0.0,
        "EXECUTING_TRAJECTORY": 14400.0,  # A 60 + B 40+30 + C 30 + D 20 + E 60 = 240 min
        "CREATING_WORKPIECE": 0.0,
        "PAUSED": 600.0,  # 200-210
        "ERROR": 600.0,  # 280-290
    }
    assert k["available_time_s"] == 28800.0  # the whole 8 h: the server was up throughout


def test_shift_operations() -> None:
    k = shift_kpis()
    assert k["operations_ended"] == 6  # cal-1, A, B, C, D, E
    assert k["operations_completed"] == 4  # cal-1, A, B, E
    assert k["operations_completed_per_hour"] == 0.5  # 4 / 8 h
    assert k["average_execution_time_s"] == {
        "trajectory": 4000.0,  # (3600 A + 4800 B incl. its pause + 3600 E) / 3
        "calibrate_robot": 600.0,
        "calibrate_camera": None,
        "create_workpiece": None,
    }
    assert k["utilization"] == 0.5  # 14400 executing / 28800 available
    assert k["workpieces_processed"] == 30  # A 12 + B 12 + E 6
    assert k["workpieces_failed"] == 12  # C; D was cancelled and does not count


def test_shift_faults() -> None:
    k = shift_kpis()
    assert k["errors_counted"] == 3  # 2 recoverable + 1 critical; the warning does not count
    assert k["error_rate_per_100_operations"] == 50.0  # 3 / 6 ended × 100
    assert k["failures"] == 1  # the entry into ERROR at 280
    assert k["mtbf_s"] == 28200.0  # (28800 - 600 in ERROR) / 1
    assert k["mttr_s"] == 600.0  # the one episode, 280-290
    assert k["recovery_attempts"] == 4
    assert k["error_recovery_success_rate"] == 0.5  # 2 of 4


def test_shift_oee() -> None:
    k = shift_kpis()
    assert k["oee"]["availability"] == 47 / 48  # (28800 - 600) / 28800
    # 3 completed runs × 3600 s design / 14400 s executing: the 30 min of the failed run C
    # and the 20 min of the cancelled run D are spent without a good run to show for them.
    assert k["oee"]["performance"] == 0.75
    # 2 good parts (A, E) / 5 judged (A, B, E, and the failed C and the cancelled D: parts
    # whose run did not complete are defective, as the order card counts them).
    assert k["oee"]["quality"] == 2 / 5
    assert k["oee"]["oee"] == pytest.approx(47 / 160, rel=1e-15)  # 47/48 × 3/4 × 2/5


def test_shift_quality() -> None:
    k = shift_kpis()
    assert k["quality"] == {
        "parts_good": 2,  # A, E
        "parts_defective": 3,  # B inspected; C failed and D cancelled, not inspected
        "parts_not_inspected": 0,
        "trajectory_precision_mm": {
            "mean": 0.5,  # (0.25 + 0.5 + 0.75) / 3
            "p95": 1.5,  # of [0.5, 0.75, 1.5]: the ceil(0.95 × 3) = 3rd
        },
        "dispensing_cv_percent": 6.0,  # (2 + 12 + 4) / 3
        "vision_residual_mm": 0.5,  # (0.25 + 0.75) / 2: E did not measure it
    }


def test_result_is_json() -> None:
    k = shift_kpis()
    assert json.loads(json.dumps(k, allow_nan=False)) == k


# --- Clipping ------------------------------------------------------------------------------


def test_window_clips_intervals_and_reads_rows_stamped_after_it() -> None:
    # Window 75-255 min (3 h) of the same shift.
    k = shift_kpis(Window(at(75), at(255)))
    assert k["time_in_state_s"] == {
        "INITIALIZING": 0.0,
        "IDLE": 1800.0,  # 80-90, 150-160, 240-250
        "CALIBRATING_ROBOT": 300.0,  # 70-80 clipped to 75-80
        "CALIBRATING_CAMERA": 0.0,
        # 90-150 + 160-200 + 210-240 + 250-255; the last piece is closed by the row at 280,
        # stamped after the window.
        "EXECUTING_TRAJECTORY": 8100.0,
        "CREATING_WORKPIECE": 0.0,
        "PAUSED": 600.0,
        "ERROR": 0.0,
    }
    assert k["available_time_s"] == 10800.0  # all 3 h
    assert k["operations_ended"] == 3  # cal-1 (80), A (150), B (240)
    assert k["operations_completed_per_hour"] == 1.0  # 3 / 3 h
    # A run counts whole, in the window it ended in: cal-1 started before 75 but took 600 s.
    assert k["average_execution_time_s"]["calibrate_robot"] == 600.0
    assert k["average_execution_time_s"]["trajectory"] == 4200.0  # (3600 + 4800) / 2
    assert k["utilization"] == 0.75  # 8100 / 10800
    assert k["error_rate_per_100_operations"] == 100 / 3  # 1 recoverable (120) / 3 ended
    assert k["failures"] == 0
    assert k["mtbf_s"] is None
    assert k["mttr_s"] is None
    assert k["error_recovery_success_rate"] == 1.0  # 120.5 only
    assert k["workpieces_processed"] == 24
    assert k["workpieces_failed"] == 0
    assert k["oee"] == {
        "availability": 1.0,
        "performance": 8 / 9,  # 2 × 3600 / 8100
        "quality": 0.5,  # A good, B defective
        "oee": 4 / 9,
    }
    assert k["quality"]["parts_good"] == 1
    assert k["quality"]["parts_defective"] == 1


def test_error_episode_straddling_the_window_start() -> None:
    # Window 285-480: the ERROR episode 280-290 started before it and ended inside it.
    k = shift_kpis(Window(at(285), at(480)))
    assert k["time_in_state_s"]["ERROR"] == 300.0  # only 285-290 is inside
    assert k["available_time_s"] == 11700.0  # 195 min
    assert k["failures"] == 0  # the entry at 280 belongs to the earlier window
    assert k["mtbf_s"] is None
    assert k["mttr_s"] == 600.0  # the whole episode: it was repaired in this window
    assert k["oee"]["availability"] == 38 / 39  # (11700 - 300) / 11700


def test_window_is_half_open() -> None:
    # run-A ended at exactly 150: outside [0, 150), inside [150, 300).
    before = shift_kpis(Window(at(0), at(150)))
    after = shift_kpis(Window(at(150), at(300)))
    assert before["average_execution_time_s"]["trajectory"] is None
    assert after["average_execution_time_s"]["trajectory"] == 4200.0  # A and B
    # The entry into ERROR at 280 counts once across adjacent windows.
    assert shift_kpis(Window(at(0), at(280)))["failures"] == 0
    assert shift_kpis(Window(at(280), at(480)))["failures"] == 1


def test_performance_is_capped_at_one() -> None:
    # Window 120-151: 30 min of run A executing, yet A (designed for 60 min) ended inside.
    k = shift_kpis(Window(at(120), at(151)))
    assert k["time_in_state_s"]["EXECUTING_TRAJECTORY"] == 1800.0
    assert k["oee"]["performance"] == 1.0  # min(1, 3600 × 1 / 1800)


def test_consecutive_windows_add_up_to_the_shift() -> None:
    hours = [shift_kpis(Window(at(60 * h), at(60 * (h + 1)))) for h in range(8)]
    whole = shift_kpis()
    for state in STATES:
        assert (
            math.fsum(k["time_in_state_s"][state] for k in hours)
            == (whole["time_in_state_s"][state])
        )
    assert sum(k["operations_ended"] for k in hours) == whole["operations_ended"]
    assert sum(k["failures"] for k in hours) == whole["failures"]


# --- The state the cell is in now ------------------------------------------------------------


def test_current_open_state_counts_up_to_now() -> None:
    # 0-10 INITIALIZING, 10-30 IDLE, EXECUTING since 30 with run-X under way; now = 45.
    rows, state, since = journal(
        "INITIALIZING",
        0,
        [(10, "IDLE", "SYSTEM_READY"), (30, "EXECUTING_TRAJECTORY", "START_REQUESTED")],
    )
    running = [op("run-X", "trajectory", 30, None, None, 5)]
    k = compute_kpis(
        Window(at(0), at(60)),
        rows,
        running,
        [],
        [],
        current_state=state,
        current_since=since,
        now=at(45),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )
    assert k["time_in_state_s"]["INITIALIZING"] == 600.0
    assert k["time_in_state_s"]["IDLE"] == 1200.0
    assert k["time_in_state_s"]["EXECUTING_TRAJECTORY"] == 900.0  # 30-45, still open
    assert k["available_time_s"] == 2700.0  # 45 min: the rest of the hour has not happened
    assert k["utilization"] == 1 / 3  # 900 / 2700
    assert k["operations_ended"] == 0  # run-X has not ended: not counted anywhere yet
    assert k["operations_completed_per_hour"] == 0.0
    assert k["error_rate_per_100_operations"] is None
    assert k["workpieces_processed"] == 0
    assert k["oee"] == {
        "availability": 1.0,
        "performance": 0.0,  # 15 min executing, no completed run yet
        "quality": None,  # no trajectory run ended
        "oee": None,
    }
    # A window that ends before now clips the open interval too: EXECUTING 30-40.
    durations = state_durations(
        rows, Window(at(0), at(40)), current_state=state, current_since=since, now=at(45)
    )
    assert durations["EXECUTING_TRAJECTORY"] == 600.0


def test_downtime_and_the_unclosed_state_before_a_crash_are_not_available() -> None:
    # Life 1: INITIALIZING 0-5, IDLE from 5, crashed at 20 (no closing row).
    # Life 2: started 30, INITIALIZING 30-35, IDLE since 35; now = 60.
    life1, _, _ = journal("INITIALIZING", 0, [(5, "IDLE", "SYSTEM_READY")])
    life2, state, since = journal("INITIALIZING", 30, [(35, "IDLE", "SYSTEM_READY")])
    durations = state_durations(
        life1 + life2, Window(at(0), at(60)), current_state=state, current_since=since, now=at(60)
    )
    assert durations["INITIALIZING"] == 600.0  # 0-5 + 30-35
    assert durations["IDLE"] == 1500.0  # 35-60 only: 5-20 was never closed in the journal
    assert math.fsum(durations.values()) == 2100.0


# --- Empty journals ----------------------------------------------------------------------------


def test_empty_journal_server_down_all_window() -> None:
    k = compute_kpis(
        Window(at(0), at(60)),
        [],
        [],
        [],
        [],
        current_state="INITIALIZING",
        current_since=at(120),  # started after the window
        now=at(180),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )
    assert k["time_in_state_s"] == dict.fromkeys(STATES, 0.0)
    assert k["available_time_s"] == 0.0
    assert k["operations_ended"] == 0
    assert k["operations_completed_per_hour"] == 0.0
    assert k["average_execution_time_s"] == dict.fromkeys(kpis.OPERATION_KINDS)
    for key in (
        "utilization",
        "error_rate_per_100_operations",
        "mtbf_s",
        "mttr_s",
        "error_recovery_success_rate",
    ):
        assert k[key] is None, key
    assert k["failures"] == 0
    assert k["workpieces_processed"] == 0
    assert k["workpieces_failed"] == 0
    assert k["oee"] == {"availability": None, "performance": None, "quality": None, "oee": None}
    assert json.loads(json.dumps(k, allow_nan=False)) == k


def test_empty_journal_idle_all_window() -> None:
    k = compute_kpis(
        Window(at(0), at(60)),
        [],
        [],
        [],
        [],
        current_state="IDLE",
        current_since=at(-60),  # idle since before the window
        now=at(120),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )
    assert k["time_in_state_s"]["IDLE"] == 3600.0
    assert k["available_time_s"] == 3600.0
    assert k["utilization"] == 0.0
    assert k["mtbf_s"] is None  # no failure: MTBF is unknown, not infinite
    assert k["oee"] == {"availability": 1.0, "performance": None, "quality": None, "oee": None}


# --- Edge rules ----------------------------------------------------------------------------------


def test_cancelled_only_trajectory_runs_have_no_quality() -> None:
    k = compute_kpis(
        SHIFT,
        SHIFT_TRANSITIONS,
        [op("run-D", "trajectory", 300, 320, "cancelled", 12)],
        [],
        [],
        current_state=SHIFT_STATE,
        current_since=SHIFT_SINCE,
        now=at(480),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )
    assert k["operations_ended"] == 1  # a cancelled run did end: it counts for the error rate
    # Its part did not get its whole bead: defective, as the order card counts it.
    assert (k["quality"]["parts_defective"], k["oee"]["quality"]) == (1, 0.0)
    assert k["oee"]["performance"] == 0.0
    assert k["oee"]["oee"] == 0.0
    assert k["workpieces_failed"] == 0


def test_interrupted_runs_count_as_spoiled() -> None:
    ops = [
        op("r1", "trajectory", 90, 150, "completed", 4),
        op("r2", "trajectory", 160, 240, "interrupted", 3),
        op("r3", "trajectory", 250, 280, "failed", 2),
    ]
    k = compute_kpis(
        SHIFT,
        SHIFT_TRANSITIONS,
        ops,
        [],
        [],
        current_state=SHIFT_STATE,
        current_since=SHIFT_SINCE,
        now=at(480),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )
    assert k["workpieces_processed"] == 4
    assert k["workpieces_failed"] == 5  # 3 interrupted + 2 failed
    # r1 completed without an inspection; r2 and r3 did not complete: defective parts.
    quality = k["quality"]
    assert (quality["parts_good"], quality["parts_defective"]) == (0, 2)
    assert quality["parts_not_inspected"] == 1
    assert k["oee"]["quality"] == 0.0


def kpis_of_runs(ops: list[dict[str, Any]]) -> dict[str, Any]:
    return compute_kpis(
        SHIFT,
        SHIFT_TRANSITIONS,
        ops,
        [],
        [],
        current_state=SHIFT_STATE,
        current_since=SHIFT_SINCE,
        now=at(480),
        design_cycle_time_s=DESIGN_CYCLE_S,
    )


NO_QUALITY = {
    "parts_good": 0,
    "parts_defective": 0,
    "parts_not_inspected": 2,
    "trajectory_precision_mm": {"mean": None, "p95": None},
    "dispensing_cv_percent": None,
    "vision_residual_mm": None,
}


def test_uninspected_runs_are_parts_not_inspected() -> None:
    # Completed runs with inspection off: their results carry no "inspection" key.
    ops = [
        op("r1", "trajectory", 90, 150, "completed", 4),
        op("r2", "trajectory", 160, 240, "completed", 4),
    ]
    ops[0]["result"] = {"workpieces": ["w1"], "waypoints": 12}
    k = kpis_of_runs(ops)
    assert k["workpieces_processed"] == 8  # they did spray
    assert k["quality"] == NO_QUALITY
    assert k["oee"]["quality"] is None  # not 100 %: nothing was inspected
    assert k["oee"]["oee"] is None


def test_quality_counts_only_well_formed_trajectory_inspections_ended_in_the_window() -> None:
    ops = [
        op("good", "trajectory", 90, 150, "completed", 1, inspected("good", 1.0, 2.0, 3.0, 0.5)),
        op("bad", "trajectory", 160, 240, "completed", 1, inspected("defective", None, None)),
        # A verdict the contract does not know: not guessed at, a part not inspected.
        op("odd", "trajectory", 250, 280, "completed", 1, inspected("maybe", 9.0, 9.0, 9.0, 9.0)),
        # Not a trajectory: a calibration's result is never a part.
        op("cal", "calibrate_robot", 70, 80, "completed", 0, inspected("good", 9.0, 9.0)),
        # Ended after the window: the next window's part.
        op("late", "trajectory", 330, 490, "completed", 1, inspected("defective", 9.0, 9.0)),
        # Still running.
        op("now", "trajectory", 470, None, None, 1, inspected("defective", 9.0, 9.0)),
    ]
    ops[2]["result"]["inspection"]["reasons"] = ["?"]
    k = kpis_of_runs(ops)
    assert k["quality"] == {
        "parts_good": 1,
        "parts_defective": 1,
        "parts_not_inspected": 1,  # "odd"
        # "bad" measured nothing: its nulls are left out, not taken for 0.
        "trajectory_precision_mm": {"mean": 1.0, "p95": 2.0},
        "dispensing_cv_percent": 3.0,
        "vision_residual_mm": 0.5,
    }
    assert k["oee"]["quality"] == 0.5


def test_precision_p95_is_the_nearest_rank() -> None:
    # 20 parts, p95 0.1 .. 2.0 mm: the ceil(0.95 × 20) = 19th sorted value is 1.9.
    ops = [
        op(f"r{n}", "trajectory", 90 + n, 91 + n, "completed", 1, inspected("good", 0.5, n / 10))
        for n in range(20, 0, -1)
    ]
    k = kpis_of_runs(ops)
    assert k["quality"]["trajectory_precision_mm"] == {"mean": 0.5, "p95": 1.9}
    assert k["quality"]["parts_good"] == 20
    assert k["oee"]["quality"] == 1.0


def test_unknown_state_keeps_its_time() -> None:
    rows = [
        {
            "time": at(10),
            "old_state": "HOMING",  # a state an older journal knew
            "new_state": "IDLE",
            "event": "X",
            "event_id": "e",
            "time_in_old_state": 600.0,
        }
    ]
    d = state_durations(
        rows, Window(at(0), at(20)), current_state="IDLE", current_since=at(10), now=at(20)
    )
    assert d["HOMING"] == 600.0
    assert set(STATES) < set(d)
    assert math.fsum(d.values()) == 1200.0


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError):
        Window(at(10), at(10))
    with pytest.raises(ValueError):
        Window(at(10), at(0))
    with pytest.raises(ValueError):
        Window(at(0), math.inf)
    with pytest.raises(ValueError):
        compute_kpis(
            SHIFT,
            [],
            [],
            [],
            [],
            current_state="IDLE",
            current_since=at(0),
            now=at(1),
            design_cycle_time_s=0.0,
        )
    assert Window(at(0), at(90)).hours == 1.5


# --- The documentation ---------------------------------------------------------------------------


def _docstring_formulas() -> str:
    doc = kpis.__doc__ or ""
    block = doc.split("Formulas (the same text as docs/kpis.md)::\n", 1)[1]
    return textwrap.dedent(block).strip()


def _doc_block(heading: str, language: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    section = text.split(f"\n## {heading}\n", 1)[1]
    match = re.search(rf"```{language}\n(.*?)\n```", section, re.DOTALL)
    assert match, f"no ```{language} block under '## {heading}' in docs/kpis.md"
    return match.group(1)


def test_doc_formulas_are_the_module_docstring() -> None:
    assert _doc_block("Formulas", "text").strip() == _docstring_formulas()


def test_worked_example_in_the_doc() -> None:
    # The doc prints the result for the shift above; it must be what the code computes.
    assert json.loads(_doc_block("Worked example", "json")) == shift_kpis()


# --- Property: state durations cover exactly the time the journal covers ---------------------

segment = st.tuples(st.sampled_from(STATES), st.integers(min_value=0, max_value=10_000))
life = st.tuples(
    st.integers(min_value=0, max_value=5_000),  # down time before this life starts
    st.lists(segment, min_size=1, max_size=12),
)


@given(
    lives=st.lists(life, min_size=1, max_size=4),
    origin=st.integers(min_value=-20_000, max_value=20_000),
    start=st.integers(min_value=-20_000, max_value=60_000),
    length=st.integers(min_value=1, max_value=60_000),
    tail=st.integers(min_value=0, max_value=5_000),
    scale=st.sampled_from([1.0, 0.001, 0.37]),
)
def test_durations_sum_to_the_covered_time(lives, origin, start, length, tail, scale) -> None:
    # Build a journal of several server lives separated by down time. Within a life every
    # segment but the last is closed by a transition row; the last segment of an earlier life
    # is lost in a crash; the last one of the last life is the current open state.
    rows: list[dict[str, Any]] = []
    recorded: list[tuple[float, float]] = []  # the intervals the journal actually describes
    t = T0 + origin * scale
    current: tuple[str, float] = ("INITIALIZING", t)
    for n, (down, segments) in enumerate(lives):
        t += down * scale
        for i, (state, seconds) in enumerate(segments):
            begin, t = t, t + seconds * scale
            if i < len(segments) - 1:
                nxt = segments[i + 1][0]
                rows.append(
                    {
                        "time": t,
                        "old_state": state,
                        "new_state": nxt,
                        "event": "E",
                        "event_id": f"{n}-{i}",
                        "time_in_old_state": t - begin,
                    }
                )
                recorded.append((begin, t))
            elif n == len(lives) - 1:
                current = (state, begin)
    now = t + tail * scale
    recorded.append((current[1], now))
    window = Window(T0 + start * scale, T0 + (start + length) * scale)

    durations = state_durations(
        rows, window, current_state=current[0], current_since=current[1], now=now
    )

    # Covered time computed another way: merge the intervals first, then clip the union.
    merged: list[list[float]] = []
    for a, b in sorted(recorded):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    covered = math.fsum(max(0.0, min(b, window.end) - max(a, window.start)) for a, b in merged)
    total = math.fsum(durations.values())
    assert set(STATES) <= set(durations)
    assert all(v >= 0.0 for v in durations.values())
    assert math.isclose(total, covered, rel_tol=1e-12, abs_tol=1e-6)
    assert total <= window.end - window.start + 1e-6


# --- the default window: never empty, whatever the settings and the query ----------------

UNIX = st.floats(min_value=0, max_value=1e11, allow_nan=False, allow_infinity=False)


@given(
    since=st.none() | UNIX,
    until=st.none() | UNIX,
    now=UNIX,
    shift_hours=st.floats(min_value=0, max_value=744, allow_nan=False) | st.just(3.55e-276),
)
def test_the_kpi_window_is_a_window_whatever_the_shift_and_the_query(
    since: float | None, until: float | None, now: float, shift_hours: float
) -> None:
    """`shift_hours` 3.55e-276 made every GET /kpis a 500 ("window must end after it
    starts"): the window is built here, and for any query the route lets through (since
    before until) and any shift it is a window with a length."""
    if since is not None and until is not None and since >= until:
        return  # the route refuses it with a 422 first
    window = kpis.kpi_window(since, until, now, shift_hours)
    assert window.end > window.start and window.seconds > 0
    if until is not None:
        assert window.end == until
    if since is not None:
        assert window.start == since


def test_a_subnormal_shift_is_a_minutes_window() -> None:
    window = kpis.kpi_window(None, None, 1_700_000_000.0, 3.55e-276)
    assert window.seconds == kpis.MIN_SHIFT_S

"""The shift reports' pure rules: where shifts begin and end, which stop cost what time,
how alerts are counted, and that the printable page escapes what the journal holds."""

from __future__ import annotations

import pytest

from server.views.kpis import Window
from server.views.report_html import report_page
from server.views.reports import alerts_of, parts_by_hour, shift_at, stop_reasons

DAY = 86_400.0
HOUR = 3_600.0


def test_a_day_from_six_is_cut_into_eight_hour_shifts_in_local_time() -> None:
    offset = 2 * HOUR  # UTC+2: 06:00 local is 04:00 UTC
    day = 10 * DAY + 4 * HOUR  # a production day's start, in UTC
    first = shift_at(day + 1.0, 8, 6, offset)
    assert (first.start, first.end, first.ends_day) == (day, day + 8 * HOUR, False)
    last = shift_at(day + 23 * HOUR, 8, 6, offset)
    assert (last.start, last.end, last.ends_day) == (day + 16 * HOUR, day + DAY, True)
    before = shift_at(day - 1.0, 8, 6, offset)  # 05:59:59 local: the night shift before
    assert before.end == day and before.ends_day and before.day_start == day - DAY


def test_shifts_that_do_not_divide_the_day_leave_a_shorter_last_one() -> None:
    last = shift_at(DAY - 1.0, 10, 0, 0.0)
    assert (last.start, last.end, last.ends_day) == (20 * HOUR, DAY, True)


def transition(at: float, old: str, new: str, event_id: str, in_old: float) -> dict:
    return {
        "time": at,
        "old_state": old,
        "new_state": new,
        "event": "EMERGENCY_STOP" if new == "ERROR" else "RESET",
        "event_id": event_id,
        "time_in_old_state": in_old,
    }


def test_each_stay_in_error_is_charged_to_the_fault_that_began_it_clipped_to_the_window() -> None:
    window = Window(100.0, 200.0)
    transitions = [
        transition(90.0, "IDLE", "ERROR", "e1", 5.0),  # began before the window
        transition(110.0, "ERROR", "IDLE", "r1", 20.0),  # 10 s of it inside
        transition(120.0, "EXECUTING_TRAJECTORY", "ERROR", "e2", 3.0),
        transition(150.0, "ERROR", "IDLE", "r2", 30.0),
        transition(190.0, "IDLE", "ERROR", "e3", 40.0),  # still in ERROR at the end
    ]
    faults = {
        "e1": {"code": "ROBOT_TIMEOUT", "component": "robot", "message": "no answer"},
        "e2": {"code": "GLUE_PRESSURE", "component": "glue", "message": "low"},
        "e3": {"code": "ROBOT_TIMEOUT", "component": "robot", "message": "no answer"},
    }
    stops = stop_reasons(
        transitions, faults, window, current_state="ERROR", current_since=190.0, now=205.0
    )
    assert [(s["code"], s["count"], s["seconds"]) for s in stops] == [
        ("GLUE_PRESSURE", 1, 30.0),
        ("ROBOT_TIMEOUT", 1, 20.0),  # 10 s of the first stay, 10 s of the open one
    ]


def test_alerts_are_the_warnings_counted_by_code() -> None:
    rows = [
        {"classification": "warning", "code": "SLOW", "component": "op", "message": "a"},
        {"classification": "critical", "code": "X", "component": "robot", "message": "b"},
        {"classification": "warning", "code": "SLOW", "component": "op", "message": "c"},
    ]
    found = alerts_of(rows)
    assert found["count"] == 2
    assert found["by_code"] == [
        {"code": "SLOW", "component": "op", "count": 2, "last_message": "c"}
    ]


def test_parts_are_counted_in_the_hour_their_run_ended() -> None:
    window = Window(0.0, 2.5 * HOUR)
    good = {"inspection": {"verdict": "good"}}
    bad = {"inspection": {"verdict": "defective"}}
    runs = [
        {"kind": "trajectory", "ended_at": 10.0, "result": good},
        {"kind": "trajectory", "ended_at": 2 * HOUR + 5, "result": bad},
        {"kind": "trajectory", "ended_at": 3 * HOUR, "result": good},  # after the window
        {"kind": "calibrate_robot", "ended_at": 20.0, "result": good},
        {"kind": "trajectory", "ended_at": 30.0, "result": {}},  # not inspected
    ]
    hours = parts_by_hour(runs, window)
    assert [(h["good"], h["defective"]) for h in hours] == [(1, 0), (0, 0), (0, 1)]


@pytest.mark.parametrize("evil", ["<script>alert(1)</script>", '"><img src=x onerror=1>'])
def test_the_printable_page_escapes_the_journal_s_text(evil: str) -> None:
    report = {
        "id": 3,
        "period": "shift",
        "cell_id": "cell-1",
        "window": {"start": 0.0, "end": HOUR},
        "generated_at": HOUR,
        "parts": {
            "good": 4,
            "defective": 1,
            "by_hour": [{"start": 0.0, "good": 4, "defective": 1}],
        },
        "oee": {"availability": 0.9, "performance": 0.8, "quality": 0.8, "oee": 0.576},
        "time_in_state_s": {"IDLE": 600.0, "EXECUTING_TRAJECTORY": 3000.0},
        "stop_reasons": [
            {"code": evil, "component": "robot", "message": evil, "count": 1, "seconds": 12.0}
        ],
        "alerts": {"count": 1, "by_code": [{"code": "A", "component": evil, "count": 1}]},
        "maintenance": {
            "items_due": [{"name": evil, "status": "due", "percent": 101.0, "reason": evil}],
            "pot_life": "near",
            "glue_level": "off",
        },
    }
    page = report_page(report)
    assert evil not in page
    assert page.count("<svg") >= 4 and "57.6 %" in page and "pot life: near" in page

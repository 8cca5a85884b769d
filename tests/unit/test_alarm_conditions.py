"""The alarm conditions' rules (server/opcua/conditions.py), on bus messages as the
worker publishes them: what raises, what is first-out, what clears, who may do what."""

from __future__ import annotations

from typing import Any

import pytest

from server.opcua.conditions import ConditionBook, Notice, Refused


def book() -> ConditionBook:
    return ConditionBook(f"e{n}".encode() for n in range(1, 1000))


def fault(code: str, component: str = "robot", event_id: str = "ev", **more: Any) -> dict:
    return {
        "code": code,
        "message": f"{code} happened",
        "component": component,
        "event_id": event_id,
        "classification": "critical",
        "state": "ERROR",
        "time": 100.0,
        **more,
    }


def warning(code: str, state: str) -> dict:
    return {
        "code": code,
        "message": f"{code} warned",
        "component": "op",
        "classification": "warning",
        "state": state,
    }


def moved(old: str, new: str, event: str, stop_reason: dict | None = None) -> dict:
    return {
        "old_state": old,
        "new_state": new,
        "event": event,
        "snapshot": {"state": new, "stop_reason": stop_reason},
    }


def only(notices: list[Notice]) -> Notice:
    assert len(notices) == 1, notices
    return notices[0]


def test_the_first_fault_of_a_cascade_is_the_first_out_until_the_cell_clears() -> None:
    alarms = book()
    estop = only(alarms.on_message("error", fault("EMERGENCY_STOP", "api"), 1, 100.0))
    assert estop.condition.first_out and estop.condition.severity == 1000
    lost = only(alarms.on_message("error", fault("COMM_LOST"), 2, 101.0))
    assert not lost.condition.first_out and lost.condition.severity == 800
    # A halt a device did not confirm belongs to the stop, never its reason.
    halt = {"code": "HALT_INCOMPLETE", "message": "glue: no answer", "component": "glue"}
    assert not only(alarms.on_message("error", halt, 3, 101.0)).condition.first_out
    reason = {"code": "EMERGENCY_STOP"}
    assert (
        alarms.on_message(
            "state_changed", moved("IDLE", "ERROR", "EMERGENCY_STOP", reason), 4, 101.0
        )
        == []
    )
    # The reset probes (still a stop reason), then enters IDLE without one: all clear.
    assert (
        alarms.on_message(
            "state_changed", moved("ERROR", "INITIALIZING", "RESET_REQUESTED", reason), 5, 102.0
        )
        == []
    )
    cleared = alarms.on_message(
        "state_changed", moved("INITIALIZING", "IDLE", "SYSTEM_READY"), 6, 103.0
    )
    assert {n.condition.code for n in cleared} == {"EMERGENCY_STOP", "COMM_LOST", "HALT_INCOMPLETE"}
    assert all(not n.condition.active and n.condition.retain for n in cleared)  # not acked
    again = only(alarms.on_message("error", fault("ALARM", "glue"), 7, 104.0))
    assert again.condition.first_out


def test_a_run_warning_clears_when_a_later_run_in_its_state_completes_without_it() -> None:
    alarms = book()
    alarms.on_message(
        "state_changed", moved("IDLE", "EXECUTING_TRAJECTORY", "START_REQUESTED"), 1, 1.0
    )
    raised = only(
        alarms.on_message("alert", warning("CALIBRATION_DEGRADING", "EXECUTING_TRAJECTORY"), 2, 2.0)
    )
    assert raised.condition.severity == 400 and not raised.condition.first_out
    # Its own run's completion leaves it active.
    assert (
        alarms.on_message(
            "state_changed", moved("EXECUTING_TRAJECTORY", "IDLE", "OPERATION_COMPLETED"), 3, 3.0
        )
        == []
    )
    # A calibration completing says nothing of it.
    alarms.on_message(
        "state_changed", moved("IDLE", "CALIBRATING_ROBOT", "CALIBRATE_ROBOT_REQUESTED"), 4, 4.0
    )
    assert (
        alarms.on_message(
            "state_changed", moved("CALIBRATING_ROBOT", "IDLE", "OPERATION_COMPLETED"), 5, 5.0
        )
        == []
    )
    # A failed run says nothing either.
    alarms.on_message(
        "state_changed", moved("IDLE", "EXECUTING_TRAJECTORY", "START_REQUESTED"), 6, 6.0
    )
    failed = {"code": "X"}
    alarms.on_message(
        "state_changed", moved("EXECUTING_TRAJECTORY", "ERROR", "OPERATION_FAILED", failed), 7, 7.0
    )
    assert alarms.conditions["CALIBRATION_DEGRADING"].active
    # The next spray run completing without raising it clears it.
    alarms.on_message(
        "state_changed", moved("IDLE", "EXECUTING_TRAJECTORY", "START_REQUESTED"), 8, 8.0
    )
    cleared = alarms.on_message(
        "state_changed", moved("EXECUTING_TRAJECTORY", "IDLE", "OPERATION_COMPLETED"), 9, 9.0
    )
    assert [n.condition.code for n in cleared] == ["CALIBRATION_DEGRADING"]


def test_the_error_timeout_warning_clears_when_the_cell_leaves_error() -> None:
    alarms = book()
    only(alarms.on_message("alert", warning("ERROR_STATE_TIMEOUT", "ERROR"), 1, 1.0))
    cleared = alarms.on_message(
        "state_changed", moved("ERROR", "INITIALIZING", "RESET_REQUESTED", {"code": "X"}), 2, 2.0
    )
    assert [n.condition.code for n in cleared] == ["ERROR_STATE_TIMEOUT"]


def test_acknowledge_and_confirm_follow_the_condition_model() -> None:
    alarms = book()
    raised = only(alarms.on_message("error", fault("EMERGENCY_STOP", "api"), 1, 1.0)).condition
    assert (raised.acked, raised.confirmed, raised.retain) == (False, True, True)
    assert (
        alarms.confirm("EMERGENCY_STOP", raised.event_id, "", "op", 2.0)
        is Refused.ALREADY_CONFIRMED
    )
    assert alarms.acknowledge("NOPE", raised.event_id, "", "op", 2.0) is Refused.UNKNOWN_CONDITION
    assert alarms.acknowledge("EMERGENCY_STOP", b"old", "", "op", 2.0) is Refused.EVENT_ID_UNKNOWN
    acked = alarms.acknowledge("EMERGENCY_STOP", raised.event_id, "seen", "op", 2.0)
    assert isinstance(acked, Notice)
    assert (acked.condition.acked, acked.condition.confirmed) == (True, False)
    assert acked.condition.event_id != raised.event_id and acked.condition.user == "op"
    assert acked.condition.retain  # still active
    assert (
        alarms.check("Acknowledge", "EMERGENCY_STOP", acked.condition.event_id)
        is Refused.ALREADY_ACKED
    )
    confirmed = alarms.confirm("EMERGENCY_STOP", acked.condition.event_id, "fixed", "tech", 3.0)
    assert isinstance(confirmed, Notice) and confirmed.condition.confirmed
    cleared = only(
        alarms.on_message("state_changed", moved("INITIALIZING", "IDLE", "SYSTEM_READY"), 2, 4.0)
    )
    assert not cleared.condition.active and not cleared.condition.retain
    assert alarms.retained() == []


@pytest.mark.parametrize(
    ("code", "classification", "severity"),
    [
        ("EMERGENCY_STOP", "critical", 1000),
        ("COMM_LOST", "critical", 800),
        ("MARKER_NOT_FOUND", "recoverable", 600),
        ("SLOW_OPERATION", "warning", 400),
    ],
)
def test_severity_follows_the_classification(code: str, classification: str, severity: int) -> None:
    kind = "alert" if classification == "warning" else "error"
    notice = only(book().on_message(kind, fault(code, classification=classification), 1, 1.0))
    assert notice.condition.severity == severity


def test_a_care_warning_clears_when_the_cell_says_its_cause_has_gone() -> None:
    """`alert_cleared` (a maintenance item done, a refill, a purge): the warning of that
    code goes inactive; retained until acknowledged, as every cleared alarm."""
    alarms = book()
    due = only(alarms.on_message("alert", warning("MAINTENANCE_DUE", "IDLE"), 1, 1.0))
    assert due.condition.active
    # A clear of a code never raised, or of a fault's code, changes nothing.
    assert alarms.on_message("alert_cleared", {"code": "GLUE_LEVEL_LOW"}, 2, 2.0) == []
    only(alarms.on_message("error", fault("ALARM", "glue"), 3, 3.0))
    assert alarms.on_message("alert_cleared", {"code": "ALARM"}, 4, 4.0) == []
    assert alarms.conditions["ALARM"].active
    cleared = only(alarms.on_message("alert_cleared", {"code": "MAINTENANCE_DUE"}, 5, 5.0))
    assert cleared.why == "cleared"
    assert not cleared.condition.active and cleared.condition.changed_at == 5.0
    assert cleared.condition.retain  # nobody acknowledged it yet
    # Cleared once: a second clear sends nothing.
    assert alarms.on_message("alert_cleared", {"code": "MAINTENANCE_DUE"}, 6, 6.0) == []
    # Acknowledged after the clear: no longer retained.
    acked = alarms.acknowledge("MAINTENANCE_DUE", cleared.condition.event_id, "", "op", 7.0)
    assert isinstance(acked, Notice) and not acked.condition.retain
    # Raised again later: active again, waiting for a new acknowledgement.
    again = only(alarms.on_message("alert", warning("MAINTENANCE_DUE", "IDLE"), 8, 8.0))
    assert again.condition.active and not again.condition.acked

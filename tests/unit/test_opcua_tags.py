"""The OPC UA tags' pure parts: the PackML mapping, and what Status, Admin and CellState hold."""

from __future__ import annotations

import json
import math

from server.core.machine.transitions import State
from server.opcua import tags
from server.opcua.packml import PACKML_STATE, PackMLState, UnitMode, packml_state, unit_mode


def test_every_cell_state_has_a_packml_state_and_a_mode() -> None:
    assert set(PACKML_STATE) == set(State)
    assert packml_state(State.IDLE) is PackMLState.IDLE
    assert packml_state(State.PAUSED) is PackMLState.HELD
    assert packml_state(State.ERROR) is PackMLState.ABORTED
    assert unit_mode(State.EXECUTING_TRAJECTORY) is UnitMode.PRODUCE
    assert unit_mode(State.CALIBRATING_CAMERA) is UnitMode.MAINTENANCE


def test_admin_figures_are_the_kpis_with_nan_for_unknown() -> None:
    kpis = {
        "oee": {"oee": None, "availability": 0.5, "performance": None, "quality": 1.0},
        "mtbf_s": None,
        "mttr_s": 12.5,
        "time_in_state_s": {"IDLE": 30.0},
        "workpieces_processed": 3,
        "workpieces_failed": 1,
        "quality": {"parts_good": 5, "parts_defective": 2},
    }
    figures = tags.admin_figures(kpis)
    assert figures["OEEAvailability"] == 0.5 and figures["MTTR"] == 12.5
    assert math.isnan(figures["OEE"]) and math.isnan(figures["MTBF"])
    assert figures["TimeInState.IDLE"] == 30.0 and figures["TimeInState.ERROR"] == 0.0
    # Inspected parts, not workpieces sprayed: 5 good + 2 defective processed, 2 defective.
    assert tags.admin_counts(kpis) == {"ProdProcessedCount": 7, "ProdDefectiveCount": 2}
    assert tags.admin_counts({"workpieces_processed": 3}) == {
        "ProdProcessedCount": 0,
        "ProdDefectiveCount": 0,
    }
    assert tags.same(math.nan, math.nan) and not tags.same(1.0, math.nan)


def test_cell_state_names_the_run_waypoint_and_devices() -> None:
    snapshot = {
        "state": "EXECUTING_TRAJECTORY",
        "since": 10.0,
        "operation": None,
        "stop_reason": None,
    }
    progress = {
        "operation": "trajectory",
        "run_id": "r1",
        "waypoint": 4,
        "total": 9,
        "workpiece_id": "demo",
    }
    devices = {
        "robot": {"connected": True, "last_error": None, "active_faults": [], "last_rtt_ms": 1.2}
    }
    document = json.loads(tags.encode(tags.cell_state(snapshot, progress, devices, seq=7)))
    assert document["run_id"] == "r1" and document["waypoint"] == 4
    assert document["workpiece_id"] == "demo" and document["total"] == 9
    assert document["seq"] == 7
    assert document["devices"] == {
        "robot": {"connected": True, "last_error": None, "active_faults": []}
    }


def test_stop_reason_is_the_first_out_code_and_text() -> None:
    snapshot = {
        "stop_reason": {
            "code": "EMERGENCY_STOP",
            "message": "stop pressed",
            "component": "operator",
        }
    }
    assert tags.stop_reason(snapshot) == ("EMERGENCY_STOP", "stop pressed", "operator")
    assert tags.stop_reason({"stop_reason": None}) == ("", "", "")

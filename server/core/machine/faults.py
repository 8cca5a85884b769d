"""How serious a fault is (specification section 8.1), from its code.

critical     the cell is not safe to run until a person has looked: a device link
             lost, an e-stop, a safety or workspace violation, an alarm.
recoverable  the work could not be done this time but nothing is wrong with the
             cell (a marker not seen in one frame, no part found); worth an
             automatic retry when auto_recovery_enabled.
warning      worth knowing, not a stop (slow operation, ERROR held too long).

Unknown codes are critical: when in doubt, a person decides.
"""

from __future__ import annotations

from typing import Literal

Classification = Literal["critical", "recoverable", "warning"]

RECOVERABLE = frozenset(
    {
        "MARKER_NOT_FOUND",
        "WORKPIECE_NOT_FOUND",
        "WORKPIECE_NOT_MATCHED",
        "CHESSBOARD_NOT_FOUND",
        "VISION_TIMEOUT",
    }
)
WARNING = frozenset(
    {
        "ERROR_STATE_TIMEOUT",
        "SLOW_OPERATION",
        "CALIBRATION_DEGRADING",
        "JOURNAL_DAMAGED",
        "INSPECTION_NO_SPACE",  # the part is sprayed; its inspection could not be kept
        # the care meter's (server/core/worker/care.py): the cell runs on, a person plans work
        "MAINTENANCE_DUE",
        "MAINTENANCE_OVERDUE",
        "POT_LIFE_NEAR",
        "POT_LIFE_EXCEEDED",  # a start is refused until a purge; nothing stops
        "GLUE_LEVEL_LOW",
    }
)

RECOMMENDED_ACTION = {
    "EMERGENCY_STOP": "make sure the cell is clear, then reset",
    "ORDER_DEFECT_LIMIT": "check the nozzle (clogged or worn), the glue supply and the "
    "calibration (camera or table moved); then reset, and resume the order",
    "COMM_LOST": "check the robot controller is on and its network cable, then reset",
    "NO_REPLY": "check the dispenser's power and RS-485 cable, then reset",
    "NO_ANSWER": "check the robot controller: power, fault or protective stop; then reset",
    "DEVICE_UNAVAILABLE": "check the named device is powered and connected, then reset",
    "ALARM": "clear the dispenser alarm at the dispenser, then reset",
    "PRESSURE_OUT_OF_RANGE": "check the glue supply pressure, then reset",
    "FLOW_DEVIATION": "check the nozzle for a blockage and the glue supply, then reset",
    "TEMPERATURE_OUT_OF_RANGE": "check the glue's heating or the room, then reset",
    "VALVE_UNCONFIRMED": "check the glue valve is closed at the nozzle, then the "
    "dispenser's power and RS-485 cable; then reset",
    "WORKSPACE_VIOLATION": "move the part inside the workspace or recalibrate, then reset",
    "MARKER_NOT_FOUND": "uncover or clean the named marker, check lighting, then reset",
    "WORKPIECE_NOT_FOUND": "place the part fully in view, away from the markers, then reset",
    "WORKPIECE_NOT_MATCHED": "check the part is in the library (create-workpiece), then reset",
    "INTERRUPTED": "check the part and the glue line, clean if needed, then reset",
    "NOT_CALIBRATED": "reset, then run calibrate-robot",
    "WORKPIECE_EXISTS": "reset, then create the part under another id or edit it with PUT",
    "CALIBRATION_STALE": "reset, then run calibrate-robot again",
    "CALIBRATION_SCALE": "measure the markers' positions and printed side; correct "
    "marker_positions_mm (teach it: GET /calibration/markers) or marker_size_mm, reset, then run "
    "calibrate-robot",
    "CALIBRATION_HOLDOUT": "check the named marker lies flat where marker_positions_mm says, "
    "reset, then run calibrate-robot",
    "PLANNING_TIMEOUT": "coarsen the part's fill spacing or simplify its outline "
    "(PUT /workpieces/{id}), or raise planning_timeout, then reset",
    "PAUSE_NOT_HELD": "check the named device answers (valve closed, robot still), then reset",
    "JOG_FAILED": "check the robot controller (fault, protective stop) and the path of the "
    "jog, then reset",
    "PURGE_FAILED": "check the named device (robot controller, dispenser) and the purge cup "
    "at purge_position, then reset",
}


def classify(code: str) -> Classification:
    """The classification of a fault code."""
    if code in RECOVERABLE:
        return "recoverable"
    if code in WARNING:
        return "warning"
    return "critical"


def recommended_action(code: str) -> str:
    """What the technician should do first."""
    return RECOMMENDED_ACTION.get(code, "read the fault message, fix the cause, then reset")

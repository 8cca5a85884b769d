"""The operations the operational states run, by name (see transitions.OPERATION_OF_STATE)."""

from __future__ import annotations

from server.core.operations.base import (
    Operation,
    OperationContext,
    OperationResult,
    OperationWarning,
    PauseGate,
)
from server.core.operations.calibration import calibrate_camera, calibrate_robot
from server.core.operations.trajectory import execute_trajectory
from server.core.operations.workpieces import create_workpiece

__all__ = [
    "Operation",
    "OperationContext",
    "OperationResult",
    "OperationWarning",
    "PauseGate",
    "default_operations",
]


def default_operations() -> dict[str, Operation]:
    """A fresh name → operation mapping; replace entries to plug in other implementations."""
    return {
        "trajectory": execute_trajectory,
        "calibrate_robot": calibrate_robot,
        "calibrate_camera": calibrate_camera,
        "create_workpiece": create_workpiece,
    }

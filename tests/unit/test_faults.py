"""Fault classification (server/core/machine/faults.py) for every code the server raises.

The table below is the decision, code by code. A scan of the source finds every fault
code the server can produce; a new code fails `test_every_code_raised_is_in_the_table`
until someone decides here whether it is critical, recoverable (retried when
auto_recovery_enabled) or a warning.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from server.core.machine import faults
from server.core.machine.faults import classify, recommended_action

SERVER = Path(__file__).resolve().parents[2] / "server"

EXPECTED = {
    # recoverable: the work could not be done this time, the cell is fine
    "MARKER_NOT_FOUND": "recoverable",
    "WORKPIECE_NOT_FOUND": "recoverable",
    "WORKPIECE_NOT_MATCHED": "recoverable",
    "CHESSBOARD_NOT_FOUND": "recoverable",
    "VISION_TIMEOUT": "recoverable",
    # warnings: worth knowing, not a stop
    "ERROR_STATE_TIMEOUT": "warning",
    "SLOW_OPERATION": "warning",
    "CALIBRATION_DEGRADING": "warning",
    "JOURNAL_DAMAGED": "warning",  # the cell works on; the record of the past is incomplete
    "INSPECTION_NO_SPACE": "warning",  # a full disk took the image: part not inspected
    "MAINTENANCE_DUE": "warning",  # the schedule: work to plan, the cell runs on
    "MAINTENANCE_OVERDUE": "warning",
    "POT_LIFE_NEAR": "warning",
    "POT_LIFE_EXCEEDED": "warning",  # starts refused until a purge; nothing stops
    "GLUE_LEVEL_LOW": "warning",
    # critical: a person looks before the cell runs again
    "EMERGENCY_STOP": "critical",
    "COMM_LOST": "critical",
    "NO_REPLY": "critical",
    "NO_ANSWER": "critical",
    "DEVICE_UNAVAILABLE": "critical",
    "DEVICE_FAULT": "critical",
    "ALARM": "critical",
    "PRESSURE_OUT_OF_RANGE": "critical",
    "FLOW_DEVIATION": "critical",  # a wrong bead until a person looks at the nozzle
    "ORDER_DEFECT_LIMIT": "critical",  # defective parts in a row: nozzle or calibration
    "TEMPERATURE_OUT_OF_RANGE": "critical",
    "VALVE_UNCONFIRMED": "critical",  # glue may still be flowing
    "VALVE_STUCK_OPEN": "critical",
    "CAPTURE_FAILED": "critical",
    "SAFE_POSITION_FAILED": "critical",
    "JOG_FAILED": "critical",
    "PURGE_FAILED": "critical",
    "PAUSE_NOT_HELD": "critical",
    "HALT_INCOMPLETE": "critical",
    "JOURNAL_WRITE_FAILED": "critical",
    "INTERRUPTED": "critical",
    "WORKSPACE_VIOLATION": "critical",
    "PATH_EMPTY": "critical",
    "PATH_INVALID": "critical",
    "NO_WORKPIECE": "critical",
    "WORKPIECE_UNKNOWN": "critical",
    "WORKPIECE_EXISTS": "critical",
    "LIBRARY_EMPTY": "critical",
    "NOT_CALIBRATED": "critical",
    "CALIBRATION_STALE": "critical",
    "CALIBRATION_INACCURATE": "critical",
    "CALIBRATION_SCALE": "critical",
    "CALIBRATION_HOLDOUT": "critical",
    "FRAME_TOO_SMALL": "critical",
    "OPERATION_TIMEOUT": "critical",
    "PLANNING_TIMEOUT": "critical",
    "INTERNAL": "critical",
}

_CODE = re.compile(r"[A-Z][A-Z0-9]*(?:_[A-Z0-9]+)*")
# Calls whose first argument is a fault code (the drivers' and worker's reporting helpers).
_FIRST_ARG_IS_CODE = {"OperationError", "OperationWarning", "_frame_failed", "_link_lost",
                      "_report", "warn"}  # fmt: skip


def _code(node: ast.AST | None) -> str | None:
    if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
        return None
    return node.value if _CODE.fullmatch(node.value) else None


def _codes_in(tree: ast.AST) -> set[str]:
    """String constants in a code position: what a fault, warning or outcome is built from."""
    found: set[str | None] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.id if isinstance(func, ast.Name) else getattr(func, "attr", "")
            if name in _FIRST_ARG_IS_CODE and node.args:
                found.add(_code(node.args[0]))
            if name == "DeviceFault" and len(node.args) > 1:  # DeviceFault(device, code, ...)
                found.add(_code(node.args[1]))
            found.update(_code(kw.value) for kw in node.keywords if kw.arg == "code")
        elif isinstance(node, ast.Dict):
            found.update(
                _code(v)
                for k, v in zip(node.keys, node.values, strict=True)
                if isinstance(k, ast.Constant) and k.value == "code"
            )
        elif isinstance(node, ast.Assign):  # code = "X" or code, message = "X", ...
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id == "code":
                    found.add(_code(node.value))
                elif isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    for t, v in zip(target.elts, node.value.elts, strict=False):
                        if isinstance(t, ast.Name) and t.id == "code":
                            found.add(_code(v))
    return {c for c in found if c is not None}


def codes_raised() -> dict[str, list[str]]:
    """Every fault code in the server's source, with where it is produced."""
    where: dict[str, list[str]] = {}
    for path in sorted(SERVER.rglob("*.py")):
        if path.name == "faults.py":
            continue
        for code in _codes_in(ast.parse(path.read_text(encoding="utf-8"))):
            where.setdefault(code, []).append(str(path.relative_to(SERVER.parent)))
    return where


RAISED = codes_raised()


def test_the_scan_finds_codes_from_every_kind_of_producer() -> None:
    # one per producer kind, so a scan that silently finds nothing fails here
    kinds = {
        "WORKSPACE_VIOLATION": "OperationError(code, ...)",
        "CALIBRATION_DEGRADING": "OperationWarning(code, ...)",
        "COMM_LOST": "a driver's _link_lost / _frame_failed(code, ...)",
        "NO_ANSWER": "DeviceFault(device, code, ...)",
        "ALARM": "the glue driver's _report(code, ...)",
        "DEVICE_FAULT": "RunOutcome(code=...)",
        "EMERGENCY_STOP": "code, message = ...",
        "SLOW_OPERATION": "alerts.warn(code, ...)",
    }
    missing = {code: kind for code, kind in kinds.items() if code not in RAISED}
    assert not missing, f"the scan no longer finds: {missing}"


def test_every_code_raised_is_in_the_table() -> None:
    undecided = {code: where for code, where in RAISED.items() if code not in EXPECTED}
    assert not undecided, f"classify these codes in EXPECTED (and faults.py): {undecided}"


def test_the_table_holds_no_code_that_is_never_raised() -> None:
    assert set(EXPECTED) - set(RAISED) == set()


@pytest.mark.parametrize("code", sorted(EXPECTED))
def test_each_code_is_classified_as_decided(code: str) -> None:
    assert classify(code) == EXPECTED[code]


def test_every_code_named_in_faults_py_is_one_the_server_raises() -> None:
    # A misspelt entry would leave the real code at the default: critical, no retry.
    named = faults.RECOVERABLE | faults.WARNING | set(faults.RECOMMENDED_ACTION)
    assert named - set(RAISED) == set()


def test_no_code_is_both_recoverable_and_a_warning() -> None:
    assert not faults.RECOVERABLE & faults.WARNING


@pytest.mark.parametrize("code", ["", "SOMETHING_NEW", "marker_not_found", "COMM_LOST "])
def test_unknown_codes_are_critical(code: str) -> None:
    assert classify(code) == "critical"


def test_an_unknown_code_gets_the_generic_action() -> None:
    action = recommended_action("SOMETHING_NEW")
    assert action == "read the fault message, fix the cause, then reset"


@pytest.mark.parametrize("code", sorted(c for c, k in EXPECTED.items() if k == "critical"))
def test_every_critical_code_has_a_recommended_action_ending_in_reset(code: str) -> None:
    action = recommended_action(code)
    assert action.strip()
    assert action.endswith("reset") or "reset," in action


def test_the_specific_actions_are_for_codes_that_stop_the_cell() -> None:
    for code, action in faults.RECOMMENDED_ACTION.items():
        assert action.strip(), code
        assert classify(code) != "warning", f"{code} is a warning: nothing to reset"

"""A run's progress has the same field names on every transport.

The operations report progress in PROGRESS_FIELDS' names (checked on their sources);
the WebSocket and GET /state carry that record as it is; MQTT's `progress` message and
OPC UA's CellState carry the fields they forward under the same names, with the same
values.
"""

from __future__ import annotations

import ast
from pathlib import Path

from server.core.operations.base import PROGRESS_FIELDS
from server.mqtt.topics import progress_message
from server.opcua import tags

OPERATIONS = Path(__file__).resolve().parents[2] / "server" / "core" / "operations"

RECORD = {
    "run_id": "r-1",
    "operation": "trajectory",
    "step": "spraying",
    "waypoint": 4,
    "total": 9,
    "fraction": 0.4444,
    "workpiece_id": "demo",
}


def reported_keys() -> set[str]:
    """Every key of a dict literal passed to `ctx.report(...)` in the operations."""
    keys: set[str] = set()
    for path in OPERATIONS.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "report"
                and node.args
                and isinstance(node.args[0], ast.Dict)
            ):
                keys |= {k.value for k in node.args[0].keys if isinstance(k, ast.Constant)}
    return keys


def test_the_operations_report_only_the_progress_vocabulary() -> None:
    keys = reported_keys()
    assert keys, "no ctx.report call found"
    assert keys <= set(PROGRESS_FIELDS), sorted(keys - set(PROGRESS_FIELDS))


def test_mqtt_progress_uses_the_same_names_and_values() -> None:
    message = progress_message("cell-1", RECORD)
    assert message is not None
    shared = set(message) & set(PROGRESS_FIELDS)
    assert shared == {"step", "waypoint", "total", "fraction", "workpiece_id"}
    assert {key: message[key] for key in shared} == {key: RECORD[key] for key in shared}
    assert message["run_id"] == RECORD["run_id"]


def test_opcua_cell_state_uses_the_same_names_and_values() -> None:
    document = tags.cell_state({"state": "EXECUTING_TRAJECTORY"}, RECORD, {}, seq=1)
    shared = set(document) & set(PROGRESS_FIELDS)
    assert shared == {"waypoint", "total", "workpiece_id"}
    assert {key: document[key] for key in shared} == {key: RECORD[key] for key in shared}
    assert document["run_id"] == RECORD["run_id"]


def test_no_transport_uses_the_old_names() -> None:
    old = {"of", "percent", "workpiece"}
    message = progress_message("cell-1", RECORD) or {}
    document = tags.cell_state({"state": "IDLE"}, RECORD, {}, seq=1)
    assert not old & set(message) and not old & set(document)

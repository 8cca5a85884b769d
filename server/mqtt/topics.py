"""The MQTT topic contract: the topics' names and each message's JSON, built purely.

Under `<prefix>/<cell_id>/` (prefix `mqtt_topic_prefix`, default `glue`):

- `status`: retained, `{"status": "online", "time": ...}` from each connection; a clean
  stop says `offline` with its time, the last will `offline` with a null time;
- `state`: retained, the state with its since, stop reason, run and workpiece;
- `event`: one per transition, in order (`seq` is the bus's number), with the
  WebSocket's names (`old_state`, `new_state`, `timestamp`, `time_in_old_state`);
- `progress`: a run's progress; `alert`: each warning and each fault;
- `run`: one per run that ended, with its outcome and its part's one verdict
  (server/quality/part_verdict.py: good, defective or not_inspected, with why; null for
  a run that makes no part);
- `kpis`, `health`: retained, what GET /kpis and GET /health answer;
- `report`: retained, the latest shift or daily report (GET /reports/{id}'s JSON, its id
  as `report_id`);
- `command/<name>`: commands in (off by default), answered on the v5 response topic.

Why JSON built here and not the bus message as it is: the plant reads a
contract that must not change when the WebSocket's messages grow a field, and
every message names its cell, so a subscriber to `glue/+/event` needs no topic
parsing. The line view and docs/plant-integration.md read these names.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from server.core.worker.runs import RunEnded
from server.quality.part_verdict import verdict_details


@dataclass(frozen=True, slots=True)
class Topics:
    """The topic names of one cell."""

    prefix: str
    cell_id: str

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.cell_id}"

    @property
    def status(self) -> str:
        return f"{self.base}/status"

    @property
    def state(self) -> str:
        return f"{self.base}/state"

    @property
    def event(self) -> str:
        return f"{self.base}/event"

    @property
    def progress(self) -> str:
        return f"{self.base}/progress"

    @property
    def run(self) -> str:
        return f"{self.base}/run"

    @property
    def alert(self) -> str:
        return f"{self.base}/alert"

    @property
    def kpis(self) -> str:
        return f"{self.base}/kpis"

    @property
    def report(self) -> str:
        return f"{self.base}/report"

    @property
    def health(self) -> str:
        return f"{self.base}/health"

    @property
    def commands(self) -> str:
        """The subscription filter of every command topic."""
        return f"{self.base}/command/+"

    def command_name(self, topic: str) -> str | None:
        """The command a topic names (`.../command/<name>`), or None if it names none."""
        head = f"{self.base}/command/"
        if not topic.startswith(head):
            return None
        name = topic[len(head) :]
        return name if name and "/" not in name else None


def encode(message: dict[str, Any]) -> bytes:
    """Compact JSON, UTF-8."""
    return json.dumps(message, separators=(",", ":"), ensure_ascii=False).encode()


def state_message(
    cell_id: str, snapshot: dict[str, Any], run: dict[str, Any] | None
) -> dict[str, Any]:
    """The retained state from a state snapshot (GET /state's) and the run, if any."""
    reason = snapshot.get("stop_reason")
    operation = snapshot.get("operation") or {}
    run = run or {}
    return {
        "cell_id": cell_id,
        "state": snapshot["state"],
        "since": snapshot["since"],
        "stop_reason": ({"code": reason["code"], "message": reason["message"]} if reason else None),
        "run_id": run.get("run_id") or operation.get("run_id"),
        "workpiece_id": run.get("workpiece_id"),
        "operation": run.get("name") or operation.get("name"),
        "available_commands": snapshot.get("available_commands", []),
    }


def event_message(cell_id: str, seq: int, data: dict[str, Any]) -> dict[str, Any]:
    """One transition from a `state_changed` bus record, with the WebSocket's names.

    `from`, `to` and `at` are the names this topic had before it took the WebSocket's
    (`old_state`, `new_state`, `timestamp`); they are still sent, with the same values,
    until the next release (README, "Changes")."""
    return {
        "cell_id": cell_id,
        "seq": seq,
        "old_state": data["old_state"],
        "new_state": data["new_state"],
        "event": data["event"],
        "event_id": data["event_id"],
        "timestamp": data["timestamp"],
        "time_in_old_state": data.get("time_in_old_state"),
        "source": data.get("source"),
        "from": data["old_state"],
        "to": data["new_state"],
        "at": data["timestamp"],
    }


def progress_message(cell_id: str, data: dict[str, Any]) -> dict[str, Any] | None:
    """A run's progress from a `progress` bus record; None for one that reports no progress
    (a recovery attempt: its fault, if it fails, comes as an alert)."""
    if "waypoint" not in data and "fraction" not in data:
        return None
    progress = {
        "cell_id": cell_id,
        "run_id": data.get("run_id"),
        "operation": data.get("operation"),
        "state": data.get("state"),
        "waypoint": data.get("waypoint"),
        "total": data.get("total"),
        "fraction": data.get("fraction"),
        "workpiece_id": data.get("workpiece_id"),
        "step": data.get("step"),
    }
    if "views" in data:  # a camera calibration counts views, not waypoints
        progress["views"] = data["views"]
    return progress


def run_message(cell_id: str, ended: RunEnded, at: float) -> dict[str, Any]:
    """A run that ended (from CellView's run-ended hook): how, and its part's verdict.

    Every operation's end is told (a calibration too, with a null verdict), so a
    plant counts runs and parts from one topic; the inspection summary rides along
    so a reject gate or a historian needs no second request.
    """
    return {
        "cell_id": cell_id,
        "run_id": ended.run_id,
        "operation": ended.operation,
        "outcome": ended.outcome,
        "seconds": round(ended.seconds, 3),
        "workpieces": ended.workpieces,
        "error": ended.error,
        "at": at,
        **verdict_details(ended.operation, ended.outcome, ended.result, ended.error),
    }


def alert_message(cell_id: str, kind: str, at: float, data: dict[str, Any]) -> dict[str, Any]:
    """A warning (`alert` record) or a fault (`error` record), with what to do first.

    The WebSocket's names (`time`, `event_id`); `at`, this topic's old name of `time`,
    is still sent until the next release (README, "Changes")."""
    return {
        "cell_id": cell_id,
        "kind": "warning" if kind == "alert" else "fault",
        "code": data.get("code"),
        "message": data.get("message"),
        "component": data.get("component"),
        "event_id": data.get("event_id"),
        "classification": data.get("classification"),
        "recommended_action": data.get("recommended_action"),
        "state": data.get("state"),
        "time": data.get("time", at),
        "at": data.get("time", at),
    }


def status_message(
    cell_id: str, status: str, time: float | None, *, clean: bool, online_since: float | None
) -> bytes:
    """The retained liveness: `online` when connected, `offline` at a clean stop or as the
    last will, with the time as the cell's other messages carry it (Unix seconds).

    The will is handed to the broker at connect and published by it later, so it cannot
    know when the cell fell silent: its `time` is null, `clean` false, and `online_since`
    says which connection was lost."""
    message = {"cell_id": cell_id, "status": status, "time": time, "clean": clean}
    if online_since is not None:
        message["online_since"] = online_since
    return encode(message)

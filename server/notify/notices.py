"""What the cell tells a webhook: a notice per fault, alert, state change, completed run
or part (every spray run's, whatever its outcome, with the verdict every path gives it).

Built from what the cell already says (the bus's `error`, `alert` and
`state_changed` records, and the run-ended hook of CellView), so a notice never
says anything the HMI was not told. Pure functions: no I/O, no clock.

The body a webhook receives is `{id, cell_id, kind, at, state, ...details}`:
`id` names the notice for that webhook (the same on every attempt, so a receiver
dedupes a retry whose first answer was lost), `at` is when it happened (Unix
time), `state` the cell's state then.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from server.core.infra.bus import BusMessage
from server.core.worker.runs import RunEnded
from server.quality.part_verdict import verdict_details
from server.settings.webhooks import NoticeKind

# Bus record type -> the notice kind it makes.
KIND_OF_BUS_TYPE: dict[str, NoticeKind] = {
    "error": "fault",
    "alert": "alert",
    "state_changed": "state",
    "report": "report",  # a shift or daily report (server/views/reports.py)
}
BUS_TYPES = tuple(KIND_OF_BUS_TYPE)
STATE_DETAILS = ("old_state", "new_state", "event", "event_id", "source", "time_in_old_state")
HEAD = ("id", "cell_id", "kind", "at", "state")


@dataclass(frozen=True, slots=True)
class Notice:
    """One thing to tell the plant, before it is addressed to a webhook."""

    kind: NoticeKind
    at: float
    state: str
    details: dict[str, Any] = field(default_factory=dict)

    def body(self, delivery_id: str, cell_id: str) -> bytes:
        """The JSON body for one webhook (the head's keys win over a detail's)."""
        head: dict[str, Any] = {"id": delivery_id, "cell_id": cell_id, "kind": self.kind}
        head |= {"at": self.at, "state": self.state}
        document = head | {k: v for k, v in self.details.items() if k not in HEAD}
        return json.dumps(document, default=str, separators=(",", ":")).encode()


def from_bus(message: BusMessage, current_state: Callable[[], str]) -> Notice | None:
    """The notice a bus record makes, or None for a record no webhook hears of."""
    kind = KIND_OF_BUS_TYPE.get(message.type)
    data = message.data
    if kind is None:
        return None
    if kind == "state":
        snapshot = data.get("snapshot") or {}
        details = {key: data.get(key) for key in STATE_DETAILS}
        details["stop_reason"] = snapshot.get("stop_reason")
        details["seq"] = message.seq
        return Notice(kind, float(data.get("timestamp", message.time)), data["new_state"], details)
    state = str(data.get("state") or current_state())
    details = {key: value for key, value in data.items() if key != "state"}
    details["seq"] = message.seq
    return Notice(kind, float(data.get("time", message.time)), state, details)


def from_run(ended: RunEnded, at: float) -> Notice | None:
    """The notice of a completed run (a failed or cancelled one is told as fault and state)."""
    if ended.outcome != "completed":
        return None
    details = {
        "run_id": ended.run_id,
        "operation": ended.operation,
        "seconds": round(ended.seconds, 3),
        "workpieces": ended.workpieces,
        "result": ended.result,
        # verdict, inspected, reasons, label, inspection: the part's, as every path says it
        **verdict_details(ended.operation, ended.outcome, ended.result, ended.error),
    }
    return Notice("run_completed", at, ended.state, details)


def from_part(ended: RunEnded, at: float) -> Notice | None:
    """The notice of the part a spray run made, however the run ended: a part stopped by
    STOP is told too, defective and not inspected, as the order card and the KPIs count it
    (server/quality/part_verdict.py). None for a run that makes no part."""
    if ended.operation != "trajectory":
        return None
    details = {
        "run_id": ended.run_id,
        "outcome": ended.outcome,
        "error": ended.error,
        "workpieces": ended.workpieces,
        "order_id": ended.params.get("order_id"),
        **verdict_details(ended.operation, ended.outcome, ended.result, ended.error),
    }
    return Notice("part", at, ended.state, details)

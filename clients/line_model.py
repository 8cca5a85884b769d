"""A line of cells as their MQTT topics describe it: one row per cell, folded from messages.

Each cell publishes under `<prefix>/<cell_id>/`: `status` (retained JSON whose
`status` is `online`, or `offline` at a clean stop and as its last will; a cell of
an earlier release sends the bare word, read alike), `state` (retained JSON: state,
since, stop_reason, run_id, workpiece_id), `progress` (JSON: where a run is, thinned
by the cell) and `kpis` (retained, the body of GET /kpis). This module only folds
those messages into rows, with no I/O, so `gluectl line` and its tests share one reading of the
topics; the browser's line view (clients/hmi/line_state.js) reads them the same way.

A progress message belongs to a run: it is shown only while the cell's state names
that run, so a finished run's last waypoint never lingers beside IDLE.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

DEFAULT_PREFIX = "glue"
KINDS = ("status", "state", "progress", "kpis")


@dataclass
class CellRow:
    """What the line knows of one cell; None until its topic has said."""

    cell_id: str
    online: bool | None = None
    state: str | None = None
    since: float | None = None
    stop_reason: dict[str, Any] | None = None
    run_id: str | None = None
    workpiece_id: str | None = None
    progress: dict[str, Any] | None = None
    oee: float | None = None
    _progress_run: str | None = field(default=None, repr=False)

    def shown_progress(self) -> dict[str, Any] | None:
        """The progress of the cell's current run, or None."""
        if self.progress is None or self.run_id is None or self._progress_run != self.run_id:
            return None
        return self.progress

    def as_json(self) -> dict[str, Any]:
        data = {k: v for k, v in asdict(self).items() if not k.startswith("_")}
        data["progress"] = self.shown_progress()
        return data


def split_topic(prefix: str, topic: str) -> tuple[str, str] | None:
    """(cell_id, kind) of a cell's topic under `prefix`, or None for anything else."""
    parts = topic.split("/")
    if len(parts) != 3 or parts[0] != prefix or not parts[1] or parts[2] not in KINDS:
        return None
    return parts[1], parts[2]


def _json_object(payload: bytes) -> dict[str, Any] | None:
    try:
        value = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    return value if isinstance(value, dict) else None


def _ratio(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


class LineModel:
    """Every cell seen under one prefix, updated message by message."""

    def __init__(self, prefix: str = DEFAULT_PREFIX) -> None:
        self.prefix = prefix
        self.cells: dict[str, CellRow] = {}

    def apply(self, topic: str, payload: bytes) -> bool:
        """Fold one message in; False if it is not a cell's topic or not readable.

        An empty payload is a retained message being cleared: that topic's facts go.
        """
        found = split_topic(self.prefix, topic)
        if found is None:
            return False
        cell_id, kind = found
        row = self.cells.setdefault(cell_id, CellRow(cell_id))
        if kind == "status":
            row.online = _liveness(payload)
            return True
        body = _json_object(payload) if payload else {}
        if body is None:
            return False
        if kind == "state":
            row.state = body.get("state")
            row.since = _ratio(body.get("since"))
            reason = body.get("stop_reason")
            row.stop_reason = reason if isinstance(reason, dict) else None
            row.run_id = body.get("run_id")
            row.workpiece_id = body.get("workpiece_id")
        elif kind == "progress":
            row.progress = body or None
            row._progress_run = body.get("run_id")
        elif kind == "kpis":
            oee = body.get("oee")
            row.oee = _ratio(oee.get("oee")) if isinstance(oee, dict) else None
        return True

    def rows(self) -> list[CellRow]:
        """The cells in the order of their ids."""
        return [self.cells[cell_id] for cell_id in sorted(self.cells)]

    def as_json(self) -> dict[str, Any]:
        return {"prefix": self.prefix, "cells": [row.as_json() for row in self.rows()]}


def _liveness(payload: bytes) -> bool | None:
    """True online, False offline, None unknown: from `{"status": ...}` or the bare word."""
    word: Any = payload.decode("utf-8", "replace").strip()
    if word.startswith("{"):
        body = _json_object(payload)
        word = body.get("status") if body else None
    return {"online": True, "offline": False}.get(word) if isinstance(word, str) else None

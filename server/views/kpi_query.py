"""The KPIs of a window of the journal, as GET /kpis, MQTT and OPC UA read them.

One query for every reader: the HTTP route (server/api/analytics.py), the MQTT
link's retained `kpis` message and OPC UA's Admin tags call `kpis_of`, so the
figures agree; the arithmetic is server/views/kpis.py's.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any, Protocol

from server.core.machine.transitions import State
from server.settings.kpis import KpiSettings
from server.storage.journal import Journal
from server.views.kpis import compute_kpis, kpi_window

KPI_ROW_LIMIT = 100_000  # the most rows of each table one window reads


class _StateView(Protocol):
    @property
    def state(self) -> State: ...
    @property
    def since(self) -> float: ...


class RunningCell(Protocol):
    """What the KPIs read of the running cell: its journal, state and settings."""

    @property
    def journal(self) -> Journal | None: ...
    @property
    def view(self) -> _StateView: ...
    @property
    def settings(self) -> KpiSettings: ...


def _inspected_result(row: dict[str, Any]) -> dict[str, Any] | None:
    """An operation's result as the KPIs read it (for its inspection): decoded only for a
    trajectory run that ended, the only kind that may hold one, so a window of many
    rows decodes no more JSON than it must."""
    text = row.get("result")
    if row.get("kind") != "trajectory" or row.get("ended_at") is None or not text:
        return None
    try:
        result = json.loads(text) if isinstance(text, str) else text
    except ValueError:  # a damaged record: not an inspected part, and not a 500
        return None
    return result if isinstance(result, dict) else None


async def kpis_of(
    cell: RunningCell, since: float | None = None, until: float | None = None
) -> dict[str, Any]:
    """What GET /kpis answers; without a window, the current shift. The MQTT link
    publishes the same, retained, on `kpis`, and OPC UA's Admin tags read it here."""
    now = time.time()
    window = kpi_window(since, until, now, cell.settings.shift_hours)
    start, end = window.start, window.end
    journal = cell.journal
    assert journal is not None, "the cell is not started"
    await journal.caught_up()

    state, since_state = cell.view.state.value, cell.view.since
    settings = cell.settings

    def compute() -> dict[str, Any]:
        # Every transition that closes an interval overlapping the window (the first one
        # after `end` closes the last); operations by when they ended (they start earlier).
        transitions = journal.query(
            "transitions", since=start, limit=KPI_ROW_LIMIT, newest_first=False
        )
        operations = journal.query(
            "operations", since=start - 86_400, until=end, limit=KPI_ROW_LIMIT, newest_first=False
        )
        errors = journal.query(
            "errors", since=start, until=end, limit=KPI_ROW_LIMIT, newest_first=False
        )
        recoveries = journal.query(
            "recoveries", since=start, until=end, limit=KPI_ROW_LIMIT, newest_first=False
        )
        for row in recoveries:
            row["succeeded"] = bool(row["succeeded"])
        for row in operations:
            row["result"] = _inspected_result(row)
        return compute_kpis(
            window,
            transitions,
            operations,
            errors,
            recoveries,
            current_state=state,
            current_since=since_state,
            now=min(now, end),
            design_cycle_time_s=settings.design_cycle_time_s,
        )

    return await asyncio.to_thread(compute)

"""History, operations, errors and events from the journal, KPIs, CSV export.

Every table takes the same paging and time filters (`since`, `until` as Unix
seconds, `limit`, `offset`) plus equality filters on its own columns; the
journal is read off the event loop.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import time
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import Response

from server.api.schemas import ErrorView
from server.cell import Cell
from server.core.journal import Journal
from server.core.kpis import Window, compute_kpis

router = APIRouter(tags=["analytics"])

Since = Annotated[
    float | None, Query(ge=0, le=1e11, allow_inf_nan=False, description="Unix time, inclusive")
]
Until = Annotated[
    float | None, Query(ge=0, le=1e11, allow_inf_nan=False, description="Unix time, exclusive")
]
Limit = Annotated[int, Query(ge=1, le=10_000)]
Offset = Annotated[int, Query(ge=0, le=10_000_000)]
Text = Annotated[str | None, Query(max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")]
EXPORT_LIMIT = 100_000


def _journal(request: Request) -> Journal:
    cell: Cell = request.app.state.cell
    assert cell.journal is not None
    return cell.journal


async def _page(
    request: Request,
    table: str,
    since: float | None,
    until: float | None,
    limit: int,
    offset: int,
    **filters: str | None,
) -> dict[str, Any]:
    journal = _journal(request)
    await journal.caught_up()
    wanted = {k: v for k, v in filters.items() if v is not None}
    rows, total = await asyncio.gather(
        asyncio.to_thread(
            journal.query,
            table,
            since=since,
            until=until,
            filters=wanted,
            limit=limit,
            offset=offset,
        ),
        asyncio.to_thread(journal.count, table, since=since, until=until, filters=wanted),
    )
    return {table: [_decode(row) for row in rows], "total": total, "limit": limit, "offset": offset}


def _decode(row: dict[str, Any]) -> dict[str, Any]:
    for key in ("data", "params", "progress", "result"):
        if isinstance(row.get(key), str):
            row[key] = json.loads(row[key])
    if "succeeded" in row:
        row["succeeded"] = bool(row["succeeded"])
    return row


@router.get("/history")
async def get_history(
    request: Request,
    since: Since = None,
    until: Until = None,
    old_state: Text = None,
    new_state: Text = None,
    event: Text = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> dict[str, Any]:
    """Transitions, newest first: time, old and new state, event, event id, time in old state."""
    return await _page(
        request,
        "transitions",
        since,
        until,
        limit,
        offset,
        old_state=old_state,
        new_state=new_state,
        event=event,
    )


@router.get("/operations")
async def get_operations(
    request: Request,
    since: Since = None,
    until: Until = None,
    kind: Text = None,
    outcome: Text = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> dict[str, Any]:
    """Operations, newest first: kind, start, end, outcome, result summary, error."""
    return await _page(
        request, "operations", since, until, limit, offset, kind=kind, outcome=outcome
    )


@router.get("/errors")
async def get_errors(
    request: Request,
    since: Since = None,
    until: Until = None,
    code: Text = None,
    component: Text = None,
    classification: Text = None,
    state: Text = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> dict[str, Any]:
    """Faults, newest first: code, message, component, classification, event id."""
    return await _page(
        request,
        "errors",
        since,
        until,
        limit,
        offset,
        code=code,
        component=component,
        classification=classification,
        state=state,
    )


@router.get("/events")
async def get_events(
    request: Request,
    since: Since = None,
    until: Until = None,
    type: Text = None,
    source: Text = None,
    outcome: Text = None,
    state: Text = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> dict[str, Any]:
    """Every event the worker decided, accepted or refused, with its data and message."""
    return await _page(
        request,
        "events",
        since,
        until,
        limit,
        offset,
        type=type,
        source=source,
        outcome=outcome,
        state=state,
    )


@router.get(
    "/export/{table}.csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}, 404: {"model": ErrorView}},
)
async def export_csv(
    request: Request,
    table: Literal["events", "transitions", "operations", "errors", "recoveries"],
    since: Since = None,
    until: Until = None,
) -> Response:
    """A table as CSV (oldest first, at most 100 000 rows), for spreadsheets and reports."""
    return await csv_export(_journal(request), table, since, until)


async def csv_export(
    journal: Journal,
    table: str,
    since: float | None,
    until: float | None,
    filters: dict[str, str] | None = None,
) -> Response:
    """A journal table as a CSV download, oldest first."""
    await journal.caught_up()

    def build() -> str:  # reading and formatting 100k rows is work for a thread, not the loop
        rows = journal.query(
            table, since=since, until=until, filters=filters, limit=EXPORT_LIMIT, newest_first=False
        )
        buffer = io.StringIO()
        if rows:
            writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        return buffer.getvalue()

    text = await asyncio.to_thread(build)
    filename = f"{table}-{time.strftime('%Y%m%d-%H%M%S')}.csv"
    return Response(
        text,
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


@router.get("/kpis")
async def get_kpis(request: Request, since: Since = None, until: Until = None) -> dict[str, Any]:
    """KPIs and OEE over a window (default: the current shift, the last shift_hours)."""
    cell: Cell = request.app.state.cell
    worker = cell.worker
    assert worker is not None
    now = time.time()
    end = until if until is not None else now
    start = since if since is not None else end - cell.settings.shift_hours * 3600
    if start >= end:
        raise HTTPException(422, "since must be before until")
    journal = _journal(request)
    await journal.caught_up()

    state, since_state = worker.ctx.state.value, worker.ctx.since
    settings = cell.settings

    def compute() -> dict[str, Any]:
        # Every transition that closes an interval overlapping the window (the first one
        # after `end` closes the last); operations by when they ended (they start earlier).
        transitions = journal.query(
            "transitions", since=start, limit=EXPORT_LIMIT, newest_first=False
        )
        operations = journal.query(
            "operations", since=start - 86_400, until=end, limit=EXPORT_LIMIT, newest_first=False
        )
        errors = journal.query(
            "errors", since=start, until=end, limit=EXPORT_LIMIT, newest_first=False
        )
        recoveries = journal.query(
            "recoveries", since=start, until=end, limit=EXPORT_LIMIT, newest_first=False
        )
        for row in recoveries:
            row["succeeded"] = bool(row["succeeded"])
        return compute_kpis(
            Window(start, end),
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

"""Shift and daily reports: GET /reports (the list, newest first) and GET /reports/{id}
(the whole report as JSON, or as one printable HTML page with its charts).

The reports are made at the end of each shift and production day
(server/views/reports.py) and kept in the journal's `reports` table, so they are
pruned with it (analytics_retention_days).
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response

from server.api.analytics import SQLITE_INTEGER_MAX
from server.api.schemas import ErrorView
from server.bootstrap.cell import Cell
from server.storage.journal import TABLES
from server.views.report_html import report_page

router = APIRouter(tags=["analytics"])

Period = Literal["shift", "day"]


def _summary(row: dict[str, Any]) -> dict[str, Any]:
    document = row["document"]
    return {
        "id": row["seq"],
        "period": row["kind"],
        "window": {"start": row["window_start"], "end": row["window_end"]},
        "generated_at": row["time"],
        "parts_good": document["parts"]["good"],
        "parts_defective": document["parts"]["defective"],
        "oee": (document.get("oee") or {}).get("oee"),
    }


@router.get("/reports")
async def list_reports(
    request: Request,
    period: Annotated[Period | None, Query(description="shift or day; both without it")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
) -> dict[str, Any]:
    """The shift and daily reports kept, newest first: each one's id, period, window, when
    it was made, its good and defective parts and its OEE (docs/kpis.md, "Reports")."""
    cell: Cell = request.app.state.cell
    journal = cell.journal
    assert journal is not None
    await journal.caught_up()
    filters: dict[str, str] | None = {"kind": period} if period else None
    rows = await asyncio.to_thread(journal.query, "reports", filters=filters, limit=limit)
    decode = TABLES["reports"].decode
    return {"reports": [_summary(decode(row)) for row in rows]}


@router.get(
    "/reports/{report_id}",
    responses={
        200: {"content": {"text/html": {"schema": {"type": "string"}}}},
        404: {"model": ErrorView},
    },
)
async def get_report(
    request: Request,
    report_id: Annotated[
        int,
        Path(ge=1, le=SQLITE_INTEGER_MAX, description="the report's id, as GET /reports lists"),
    ],
    format: Annotated[
        Literal["json", "html"] | None,
        Query(description="json or html (a printable page); without it, the Accept header"),
    ] = None,
) -> Any:
    """A shift or daily report: parts good and defective (and per hour), OEE and its
    factors, time in each state, the stop reasons that cost the most time, the alerts
    raised, maintenance due (docs/kpis.md, "Reports")."""
    cell: Cell = request.app.state.cell
    journal = cell.journal
    assert journal is not None
    await journal.caught_up()
    row = await asyncio.to_thread(journal.row, "reports", report_id)
    if row is None:
        raise HTTPException(404, f"no report {report_id} (never made, or pruned)")
    report = {"id": report_id, **TABLES["reports"].decode(row)["document"]}
    accept = request.headers.get("accept", "")
    if format == "html" or (format is None and accept.startswith("text/html")):
        return Response(report_page(report), media_type="text/html")
    return report

"""History, operations, errors and events from the journal, KPIs, CSV export.

Every table takes the same paging and time filters (`since`, `until` as Unix
seconds, `limit`, `offset`) plus equality filters on its own columns; the
journal is read off the event loop. A CSV export takes the same filters and
streams every matching row, page by page (`csv_export`).

The equality filters are declared once, on the columns of the journal's schema
(`FILTERS`: column, type, meaning); the routes' query parameters are built from
it, each validated and documented, and the journal refuses any other column.
The rows' columns, and which of them hold JSON or a flag, come from the same
declaration (`TABLES`).
"""

from __future__ import annotations

import asyncio
import csv
import inspect
import io
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Annotated, Any, Literal, get_args

from fastapi import APIRouter, HTTPException, Path, Query, Request
from fastapi.responses import Response, StreamingResponse

from server.api.declared_query import DeclaredQueryRoute
from server.api.kpi_views import KpisView
from server.api.schemas import ErrorView, text_body
from server.api.time_window import Since, TimeWindow, Until, time_window
from server.bootstrap.cell import Cell
from server.quality.csv_columns import INSPECTION_COLUMNS, with_inspection
from server.storage.journal import FILTERS, TABLES, Cursor, Filter, Journal
from server.views.kpi_query import kpis_of

router = APIRouter(tags=["analytics"], route_class=DeclaredQueryRoute)

Limit = Annotated[int, Query(ge=1, le=10_000)]
Offset = Annotated[int, Query(ge=0, le=10_000_000)]
TEXT_MAX_LENGTH = 64
TEXT_PATTERN = r"^[A-Za-z0-9_.:-]+$"
ExportTable = Literal["events", "transitions", "operations", "errors", "recoveries"]
EXPORT_TABLES: tuple[str, ...] = get_args(ExportTable)
# Rows read, formatted and sent at a time: what bounds an export's memory, never its length.
EXPORT_PAGE_ROWS = 5_000
# The KPI window reads at most this many rows of each table.
KEYWORD_ONLY = inspect.Parameter.KEYWORD_ONLY


def _journal(request: Request) -> Journal:
    cell: Cell = request.app.state.cell
    assert cell.journal is not None
    return cell.journal


async def _page(
    request: Request,
    table: str,
    window: TimeWindow,
    limit: int,
    offset: int,
    **filters: str | None,
) -> dict[str, Any]:
    since, until = window.since, window.until
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
    decode = TABLES[table].decode  # JSON columns parsed, flags as booleans
    return {table: [decode(row) for row in rows], "total": total, "limit": limit, "offset": offset}


def _filter_parameter(spec: Filter) -> inspect.Parameter:
    """An optional query parameter filtering a column by equality. Text is bounded in
    length and characters (TEXT_MAX_LENGTH, TEXT_PATTERN), or one of the column's values
    when they are a closed set: a value is never anything odd."""
    kind: Any = spec.type
    if spec.values:
        kind, query = Literal[spec.values], Query(description=spec.meaning)
    elif spec.type is str:
        query = Query(max_length=TEXT_MAX_LENGTH, pattern=TEXT_PATTERN, description=spec.meaning)
    else:
        query = Query(description=spec.meaning)
    return inspect.Parameter(
        spec.column, KEYWORD_ONLY, default=None, annotation=Annotated[kind | None, query]
    )


def table_route(table: str, name: str, doc: str) -> Callable[..., Awaitable[dict[str, Any]]]:
    """The JSON route of a journal table: time range, paging, and the table's filters
    (those of FILTERS offered on its JSON route), each a documented query parameter."""

    async def endpoint(
        request: Request,
        since: float | None,
        until: float | None,
        limit: int,
        offset: int,
        **filters: Any,
    ) -> dict[str, Any]:
        window = time_window(since, until)
        return await _page(request, table, window, limit, offset, **filters)

    endpoint.__name__ = endpoint.__qualname__ = name
    endpoint.__doc__ = doc
    endpoint.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
        [
            inspect.Parameter("request", KEYWORD_ONLY, annotation=Request),
            inspect.Parameter("since", KEYWORD_ONLY, default=None, annotation=Since),
            inspect.Parameter("until", KEYWORD_ONLY, default=None, annotation=Until),
            *(_filter_parameter(f) for f in FILTERS[table] if f.on_json_route),
            inspect.Parameter("limit", KEYWORD_ONLY, default=100, annotation=Limit),
            inspect.Parameter("offset", KEYWORD_ONLY, default=0, annotation=Offset),
        ],
        return_annotation=dict[str, Any],
    )
    return endpoint


# path, table (the answer's key), route name, what the rows are
TABLE_ROUTES = (
    (
        "/history",
        "transitions",
        "get_history",
        "Transitions, newest first: time, old and new state, event, event id, time in old state.",
    ),
    (
        "/operations",
        "operations",
        "get_operations",
        "Operations, newest first: kind, start, end, outcome, result summary, error.",
    ),
    (
        "/errors",
        "errors",
        "get_errors",
        "Faults, newest first: code, message, component, classification, event id.",
    ),
    (
        "/events",
        "events",
        "get_events",
        "Every event the worker decided, accepted or refused, with its data and message.",
    ),
)
for _path, _table, _name, _doc in TABLE_ROUTES:
    # `name` gives the summary and operationId, as a function of that name would.
    router.add_api_route(_path, table_route(_table, _name, _doc), methods=["GET"], name=_name)


# The largest row number SQLite stores: a larger one could only be refused by SQLite.
SQLITE_INTEGER_MAX = 2**63 - 1


@router.get("/errors/{seq}", name="get_error", responses={404: {"model": ErrorView}})
async def get_error(
    request: Request, seq: Annotated[int, Path(ge=1, le=SQLITE_INTEGER_MAX)]
) -> dict[str, Any]:
    """One fault by its number (`seq` in GET /errors): what it interrupted (`context`:
    operation, run id, workpiece, waypoint) and, when an exception caused it, the stack
    (`trace`), for a technician tracing it back to a run and its code."""
    journal = _journal(request)
    await journal.caught_up()
    found = await asyncio.to_thread(journal.row, "errors", seq)
    if found is None:
        raise HTTPException(404, f"no fault numbered {seq}: see GET /errors for the faults kept")
    return TABLES["errors"].decode(found)


EXPORT_DOC = """The {table} table as CSV, oldest first, for spreadsheets and reports.

    Every matching row, with no row limit: streamed page by page, so a long table is
    never cut short (docs/api.md says what the file holds). Takes the time window and
    the equality filters of this table (those of its JSON route, and for transitions
    also `event_id`); any other query parameter is a 422 naming it: ignored, it would
    give a file holding more than was asked for.
    """


def _export_route(table: str) -> Callable[..., Awaitable[Response]]:
    """The CSV route of one journal table: its own path, so that openapi.json lists exactly
    the filters this table takes (one route for every table could only list them all)."""

    async def endpoint(
        request: Request, since: float | None, until: float | None, **filters: Any
    ) -> Response:
        window = time_window(since, until)
        given = {column: value for column, value in filters.items() if value is not None}
        if table == "audit":  # the refusals being folded, counted so far (audit_repeats.py)
            request.app.state.audit_repeats.flush()
        return await csv_export(_journal(request), table, window.since, window.until, given)

    endpoint.__name__ = endpoint.__qualname__ = f"export_{table}_csv"
    endpoint.__doc__ = EXPORT_DOC.format(table=table)
    endpoint.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
        [
            inspect.Parameter("request", KEYWORD_ONLY, annotation=Request),
            inspect.Parameter("since", KEYWORD_ONLY, default=None, annotation=Since),
            inspect.Parameter("until", KEYWORD_ONLY, default=None, annotation=Until),
            *(_filter_parameter(f) for f in FILTERS[table]),
        ],
        return_annotation=Response,
    )
    return endpoint


for _table in EXPORT_TABLES:
    router.add_api_route(
        f"/export/{_table}.csv",
        _export_route(_table),
        methods=["GET"],
        name=f"export_{_table}_csv",
        response_class=Response,
        responses={200: {"content": text_body("text/csv")}},
    )


async def csv_export(
    journal: Journal,
    table: str,
    since: float | None,
    until: float | None,
    filters: dict[str, str] | None = None,
) -> StreamingResponse:
    """A journal table as a CSV download: every matching row, oldest first, streamed.

    Why streamed in pages: a plant's tables outgrow any row cap, and an export that
    stops at one drops the newest rows without a word. Read EXPORT_PAGE_ROWS at a
    time (keyset pages, `Journal.page_after`) and sent as each is formatted, an
    export of any length holds one page in memory.

    What the file holds: the header (from TABLES, so an empty table still has it),
    then every matching row committed before the export started (after
    `caught_up`: read-your-writes), each once. Rows written while it streams are
    left out by the rowid bound read at the start (`Journal.last_rowid`); an
    operation updated meanwhile shows its values as its page was read, and rows
    that retention deletes meanwhile may be missing. If reading fails midway the
    connection is closed before the end of the body, so the client sees an
    incomplete download, never a short file that looks whole.
    """
    await journal.caught_up()
    bound = await asyncio.to_thread(journal.last_rowid, table)
    columns = TABLES[table].column_names
    page_rows = EXPORT_PAGE_ROWS
    # The operations export carries each spray run's inspection figures (docs/quality.md).
    inspected = table == "operations"

    def pages() -> Iterator[str]:
        # A plain generator on purpose: StreamingResponse runs each step of a sync
        # iterator in the thread pool (Starlette's iterate_in_threadpool), so the
        # SQLite reads and the formatting of every page stay off the event loop.
        buffer = io.StringIO()
        writer = csv.writer(buffer)
        writer.writerow([*columns, *INSPECTION_COLUMNS] if inspected else columns)
        yield _drain(buffer)
        after: Cursor | None = None
        while True:
            rows, after = journal.page_after(
                table,
                since=since,
                until=until,
                filters=filters,
                after=after,
                bound=bound,
                limit=page_rows,
            )
            if rows:
                writer.writerows(with_inspection(columns, rows) if inspected else rows)
                yield _drain(buffer)
            if len(rows) < page_rows:
                return

    filename = f"{table}-{time.strftime('%Y%m%d-%H%M%S')}.csv"
    return StreamingResponse(
        pages(),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


def _drain(buffer: io.StringIO) -> str:
    """What was written to `buffer` since the last drain; the buffer is emptied."""
    text = buffer.getvalue()
    buffer.seek(0)
    buffer.truncate()
    return text


@router.get("/kpis", response_model=KpisView)
async def get_kpis(request: Request, since: Since = None, until: Until = None) -> dict[str, Any]:
    """KPIs and OEE over a window (default: the current shift, the last shift_hours).

    `until` defaults to now, `since` to one shift before `until`. A `since` still to
    come without an `until` is a shift that has not begun: the window is the shift
    from `since` and holds nothing yet.
    """
    time_window(since, until)  # since before until
    return await kpis_of(request.app.state.cell, since, until)

"""A run's flight recording: GET /runs/{run_id}/recording, as JSON or CSV.

The samples the flight recorder journaled (server/views/recording.py, table
`run_samples`), oldest first, with what the run page shows beside them: the
run's row (kind, times, outcome, error), the fault that stopped it (the `errors`
row whose context names the run), its inspection's verdict and reasons, and
whether its annotated image is kept. CSV (`?format=csv`, or `Accept: text/csv`)
holds the samples alone, one row each, headed by the table's columns.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response

from server.api.inspections import RunId, inspection_of
from server.api.schemas import ErrorView
from server.bootstrap.cell import Cell
from server.storage.journal import TABLES, Journal

router = APIRouter(tags=["quality"])

SAMPLE_LIMIT = 200_000  # a run of more than five hours at 10 Hz
SAMPLE_COLUMNS = tuple(c for c in TABLES["run_samples"].column_names if c != "seq")
FAULT_SLACK_S = 5.0  # a run's fault is recorded just after the run's end is stamped


def _read(journal: Journal, run_id: str) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
    """The run's `operations` row and its samples (a blocking read: call it in a thread)."""
    run = journal.operation(run_id)
    if run is None:
        return None, []
    samples = journal.query(
        "run_samples", filters={"run_id": run_id}, limit=SAMPLE_LIMIT, newest_first=False
    )
    decode = TABLES["run_samples"].decode
    return TABLES["operations"].decode(run), [decode(s) for s in samples]


def _stop_fault(journal: Journal, run: dict[str, Any]) -> dict[str, Any] | None:
    """The first fault recorded while the run was on (its context names the run), or None."""
    until = (run["ended_at"] or run["started_at"]) + FAULT_SLACK_S
    rows = journal.query(
        "errors", since=run["started_at"], until=until, limit=1000, newest_first=False
    )
    for row in rows:
        TABLES["errors"].decode(row)
        if row["context"].get("run_id") == run["run_id"] and row["classification"] != "warning":
            return {k: row[k] for k in ("seq", "time", "code", "message", "component")}
    return None


def _csv(samples: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(SAMPLE_COLUMNS)
    for sample in samples:
        writer.writerow(
            "" if sample[c] is None else int(sample[c]) if c == "valve_open" else sample[c]
            for c in SAMPLE_COLUMNS
        )
    return buffer.getvalue()


@router.get(
    "/runs/{run_id}/recording",
    responses={
        200: {"content": {"text/csv": {"schema": {"type": "string"}}}},
        404: {"model": ErrorView},
    },
)
async def get_recording(
    request: Request,
    run_id: RunId,
    format: Annotated[
        Literal["json", "csv"] | None,
        Query(description="json or csv; without it, the Accept header decides (JSON first)"),
    ] = None,
) -> Any:
    """The run's flight recording: its device samples at the live feed's rate (pose, speed,
    valve, flow, pressure, with when each device reported them), the run's outcome, the
    fault that stopped it and its inspection's verdict (docs/api.md, "Flight recorder")."""
    cell: Cell = request.app.state.cell
    journal = cell.journal
    assert journal is not None
    if cell.recorder is not None:
        cell.recorder.flush()  # the samples not yet handed to the writer, too
    await journal.caught_up()
    run, samples = await asyncio.to_thread(_read, journal, run_id)
    if run is None:
        raise HTTPException(404, f"no run {run_id!r} in the journal (never, or pruned)")
    wants_csv = format == "csv" or (
        format is None and "text/csv" in request.headers.get("accept", "")
    )
    if wants_csv:
        return Response(
            _csv(samples),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="run-{run_id}.csv"'},
        )
    fault = await asyncio.to_thread(_stop_fault, journal, run)
    inspection = await inspection_of(cell, run_id)
    images = cell.stores.inspection_images if cell.stores is not None else None
    kept = images.path(run_id) if inspection is not None and images is not None else None
    has_image = kept is not None and await asyncio.to_thread(kept.exists)
    body = {
        "run_id": run_id,
        "run": {
            k: run[k] for k in ("kind", "started_at", "ended_at", "outcome", "error", "params")
        },
        "recorded": bool(samples) or cell.settings.run_recording,
        "sample_period_s": cell.settings.device_push_interval,
        "stop_reason": fault,
        "inspection": None
        if inspection is None
        else {
            "verdict": inspection.get("verdict"),
            "reasons": inspection.get("reasons", []),
            "has_image": has_image,
        },
        "columns": list(SAMPLE_COLUMNS),
        "samples": [{c: s[c] for c in SAMPLE_COLUMNS} for s in samples],
    }
    return Response(json.dumps(body, separators=(",", ":")), media_type="application/json")

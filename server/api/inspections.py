"""A spray run's inspection: GET /runs/{run_id}/inspection (JSON) and its annotated image.

Read from the journal's `inspections` table (the row committed with the run's
end, server/quality/), so what is served is what is on record; the image is
the JPEG kept beside it (server/storage/inspection_images.py), which the
newest-kept limit may have removed while the figures stay.
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request, Response

from server.api.schemas import ErrorView, binary_body
from server.bootstrap.cell import Cell

router = APIRouter(tags=["quality"])

RunId = Annotated[
    str,
    Path(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.:-]+$",
        description="the run's id (as POST /start answered, and in /operations)",
    ),
]


async def inspection_of(cell: Cell, run_id: str) -> dict[str, Any] | None:
    """The run's inspection as journaled, or None when it has none."""
    journal = cell.journal
    assert journal is not None
    await journal.caught_up()
    rows = await asyncio.to_thread(
        journal.query, "inspections", filters={"run_id": run_id}, limit=1
    )
    if not rows:
        return None
    document: dict[str, Any] = json.loads(rows[0]["document"])
    return document


def _none(run_id: str) -> HTTPException:
    return HTTPException(
        404,
        f"run {run_id!r} has no inspection: it is no spray run, it did not complete, or it "
        "ran with inspection_enabled off",
    )


@router.get("/runs/{run_id}/inspection", responses={404: {"model": ErrorView}})
async def get_inspection(request: Request, run_id: RunId) -> dict[str, Any]:
    """The run's inspection: verdict and reasons, per segment bead width, gaps, offset and
    trajectory precision, dispensing consistency, vision accuracy, when, how long it took
    (docs/quality.md)."""
    document = await inspection_of(request.app.state.cell, run_id)
    if document is None:
        raise _none(run_id)
    return document


@router.get(
    "/runs/{run_id}/inspection.jpg",
    response_class=Response,
    responses={200: {"content": binary_body("image/jpeg")}, 404: {"model": ErrorView}},
)
async def get_inspection_image(request: Request, run_id: RunId) -> Response:
    """The run's inspection frame, annotated: the planned bead paths (green good, red a
    problem), the gaps (orange), the verdict."""
    cell: Cell = request.app.state.cell
    if await inspection_of(cell, run_id) is None:
        raise _none(run_id)
    images = cell.stores.inspection_images if cell.stores is not None else None
    jpeg = await asyncio.to_thread(images.read, run_id) if images is not None else None
    if jpeg is None:
        raise HTTPException(
            404, f"run {run_id!r}'s inspection image is no longer kept (its figures are)"
        )
    return Response(jpeg, media_type="image/jpeg")

"""Maintenance: wear counters, the schedule, pot life and glue level; marking work done.

`GET /maintenance` (viewer) shows the care meter's state
(server/core/worker/care.py). `POST /maintenance/{item}/done` restarts an item's
intervals and `POST /glue/refill` says the reservoir is full again (maintenance
role); each is put on record in the audit trail, durably, before it is made
(`audit.record_before_change`), like every other change a person makes.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request

from server.api import audit
from server.api.schemas import ErrorView
from server.core.worker.care import CareMeter, UnknownItem

router = APIRouter(tags=["maintenance"])

Item = Annotated[str, Path(min_length=1, max_length=60, description="the item's name")]


def _care(request: Request) -> CareMeter:
    worker = request.app.state.cell.worker
    assert worker is not None, "the cell is not started"
    return worker.care


@router.get("/maintenance")
async def maintenance(request: Request) -> dict[str, Any]:
    """Wear counters, each maintenance item's state (ok, due, overdue), pot life, glue level."""
    return _care(request).state()


@router.post(
    "/maintenance/{item}/done",
    responses={404: {"model": ErrorView, "description": "no maintenance item of that name"}},
)
async def maintenance_done(request: Request, item: Item) -> dict[str, Any]:
    """Mark a maintenance item done: its intervals start again from the counters now."""
    care = _care(request)
    try:
        care.item(item)
    except UnknownItem:
        names = ", ".join(i.name for i in request.app.state.settings.maintenance_items)
        raise HTTPException(404, f"no maintenance item {item!r}; items: {names}") from None
    await audit.record_before_change(request, f"maintenance item {item!r} done")
    return care.done(item)


@router.post("/glue/refill")
async def glue_refill(request: Request) -> dict[str, Any]:
    """The glue reservoir was refilled: its estimated level is full again."""
    await audit.record_before_change(request, "glue reservoir refilled")
    return _care(request).refill()

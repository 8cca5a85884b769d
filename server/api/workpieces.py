"""The workpiece library over HTTP: list, read, create, replace, delete, thumbnail.

File writes run off the event loop. Identifiers are validated before they
reach the file system. Each edit is on record before its file is written
(server/api/audit.py): 503 when the journal cannot write, 507 when the file
cannot be, and the library is left as it was.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from server.api import audit
from server.api.declared_query import DeclaredQueryRoute
from server.api.schemas import ErrorView, binary_body
from server.bootstrap.cell import Cell
from server.storage.workpieces import (
    IDENTIFIER,
    DamagedEntry,
    DamagedWorkpiece,
    Workpiece,
    WorkpieceIn,
    WorkpieceLibrary,
)

router = APIRouter(tags=["workpieces"], route_class=DeclaredQueryRoute)
WorkpieceId = Annotated[str, Path(pattern=IDENTIFIER, description="workpiece identifier")]
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorView, "description": "no such workpiece"}
}
TAKEN: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorView, "description": "the id chosen was taken meanwhile; retry"}
}
DAMAGED: dict[int | str, dict[str, Any]] = {
    409: {
        "model": ErrorView,
        "description": "the part's file is damaged: PUT repairs it, DELETE removes it",
    }
}


class WorkpieceList(BaseModel):
    workpieces: list[Workpiece]
    damaged: list[DamagedWorkpiece] = Field(
        default_factory=list,
        description="library files that cannot be read, with the reason: "
        "PUT /workpieces/{id} repairs one, DELETE removes it",
    )


async def _refuse_unplannable(body: WorkpieceIn) -> None:
    """A part the planner would refuse is a 422 naming the field, now.

    Accepted, it would be refused only by the run that sprays it: PATH_INVALID, and the
    cell in ERROR for a maintenance reset. The check takes up to half a second for the
    largest part allowed, so it runs off the event loop.
    """
    problem = await asyncio.to_thread(body.path_problem)
    if problem is not None:
        field, reason = problem
        loc = ("body", *field.split("."))
        raise RequestValidationError([{"type": "path_invalid", "loc": loc, "msg": reason}])


def _library(request: Request) -> WorkpieceLibrary:
    cell: Cell = request.app.state.cell
    assert cell.stores is not None
    return cell.stores.workpieces


def _missing(workpiece_id: str) -> HTTPException:
    return HTTPException(404, f"workpiece {workpiece_id!r} is not in the library")


def _damaged(damage: DamagedEntry) -> HTTPException:
    return HTTPException(
        409,
        f"{damage}: PUT /workpieces/{damage.workpiece_id} repairs it (maintenance), "
        "DELETE removes it",
    )


@router.get("/workpieces", response_model=WorkpieceList)
async def list_workpieces(request: Request) -> WorkpieceList:
    """Every workpiece in the library, and the files that cannot be read."""
    parts, damaged = await asyncio.to_thread(_library(request).survey)
    return WorkpieceList(workpieces=parts, damaged=damaged)


@router.post(
    "/workpieces",
    response_model=Workpiece,
    status_code=201,
    responses={**TAKEN, **audit.STORAGE_REFUSALS},
)
async def create_workpiece_from_outline(request: Request, body: WorkpieceIn) -> Workpiece:
    """Add a workpiece from a given outline (mm, table frame) and spray settings."""
    await _refuse_unplannable(body)
    library = _library(request)
    workpiece_id = await asyncio.to_thread(library.new_id)
    what = f"created workpiece {workpiece_id} ({body.name})"
    await audit.record_before_change(request, what)
    try:
        return await audit.save(
            request, what, lambda: library.create(body, workpiece_id=workpiece_id)
        )
    except FileExistsError:  # another creation took the id since it was chosen
        raise HTTPException(
            409, f"workpiece {workpiece_id!r} was created meanwhile: retry"
        ) from None


@router.get(
    "/workpieces/{workpiece_id}", response_model=Workpiece, responses={**NOT_FOUND, **DAMAGED}
)
async def get_workpiece(request: Request, workpiece_id: WorkpieceId) -> Workpiece:
    try:
        return await asyncio.to_thread(_library(request).get, workpiece_id)
    except KeyError:
        raise _missing(workpiece_id) from None
    except DamagedEntry as damage:
        raise _damaged(damage) from None


@router.put(
    "/workpieces/{workpiece_id}", response_model=Workpiece, responses=audit.STORAGE_REFUSALS
)
async def put_workpiece(
    request: Request, workpiece_id: WorkpieceId, body: WorkpieceIn
) -> Workpiece:
    """Create or replace the workpiece under this identifier (repairs a damaged file)."""
    await _refuse_unplannable(body)
    library = _library(request)
    what = f"stored workpiece {workpiece_id} ({body.name})"
    await audit.record_before_change(request, what)
    return await audit.save(request, what, lambda: library.put(workpiece_id, body))


@router.delete(
    "/workpieces/{workpiece_id}", status_code=204, responses={**NOT_FOUND, **audit.STORAGE_REFUSALS}
)
async def delete_workpiece(request: Request, workpiece_id: WorkpieceId) -> Response:
    library = _library(request)
    if not library.exists(workpiece_id):
        raise _missing(workpiece_id)
    what = f"deleted workpiece {workpiece_id}"
    await audit.record_before_change(request, what)
    try:
        await audit.save(request, what, lambda: library.delete(workpiece_id))
    except KeyError:  # deleted meanwhile
        raise _missing(workpiece_id) from None
    return Response(status_code=204)


@router.get(
    "/workpieces/{workpiece_id}/thumbnail",
    response_class=FileResponse,
    responses={200: {"content": binary_body("image/png")}, **NOT_FOUND},
)
async def get_thumbnail(request: Request, workpiece_id: WorkpieceId) -> FileResponse:
    """The part as the camera saw it when it was created (PNG)."""
    path = _library(request).thumbnail_path(workpiece_id)
    if not path.exists():
        raise HTTPException(404, f"workpiece {workpiece_id!r} has no thumbnail")
    return FileResponse(path, media_type="image/png")

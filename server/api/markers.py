"""The marker layout taught with the robot: GET the layout, teach, type, apply.

Why these routes: `marker_positions_mm` (the robot positions of ArUco markers
0-8 that the robot calibration maps to) should not be typed blind into the
configuration. A technician jogs the tool over marker N (`POST /jog`) and
records where it is (`POST /calibration/markers/draft/{marker}/teach`), or types a
position (`PUT /calibration/markers/draft/{marker}`); both go into a draft kept under
the data directory (server/storage/marker_layout.py). `POST
/calibration/markers/apply` puts the draft in force only when all nine are
there and the whole layout passes the settings' own check (the same merge as
PATCH /settings, `plan_change`), audited like any settings edit. Paths name the
marker, so every refusal does too.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field, ValidationError

from server.api import audit
from server.api.declared_query import DeclaredQueryRoute
from server.api.runtime_settings import plan_change
from server.api.schemas import ErrorView, Strict
from server.bootstrap.cell import Cell
from server.common.values import FiniteNumber
from server.core.machine.transitions import State
from server.core.operations.jog import read_pose_within
from server.settings.model import Millimetres, Settings, marker_layout_problems
from server.storage.marker_layout import MARKERS, MarkerLayoutStore

router = APIRouter(tags=["calibration"], route_class=DeclaredQueryRoute)

Marker = Annotated[int, Path(ge=0, le=MARKERS - 1, description="ArUco marker id, 0-8")]
Coordinate = Annotated[FiniteNumber, Field(ge=-10_000, le=10_000)]
REFUSED: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorView, "description": "not now: the message says why"}
}


class MarkerPosition(Strict):
    """Body of PUT /calibration/markers/draft/{marker}: its centre, robot frame, table plane."""

    x_mm: Coordinate
    y_mm: Coordinate


class LayoutProblem(BaseModel):
    field: str
    message: str
    type: str


class LayoutRefusal(BaseModel):
    """Why the draft cannot be applied: one error per marker at fault."""

    detail: str
    errors: list[LayoutProblem] = []


class MarkerLayoutChange(BaseModel):
    """The one setting an apply changes, merged and checked like PATCH /settings."""

    marker_positions_mm: list[tuple[Millimetres, Millimetres]]


def _cell(request: Request) -> Cell:
    return request.app.state.cell


def _store(request: Request) -> MarkerLayoutStore:
    stores = _cell(request).stores
    assert stores is not None, "the cell is not started"
    return stores.markers


def layout_view(settings: Settings, store: MarkerLayoutStore, cell: Cell) -> dict[str, Any]:
    """What GET /calibration/markers shows (and each change answers)."""
    in_force = [[float(x), float(y)] for x, y in settings.marker_positions_mm]
    taught = store.applied is not None and [tuple(p) for p in in_force] == store.applied
    robot = cell.devices.robot.health.details
    view = cell.view
    return {
        "in_force": in_force,
        "source": "taught" if taught else "settings",
        "applied_at": store.applied_at if taught else None,
        "draft": [None if m is None else m.as_dict() for m in store.draft],
        "missing": store.missing(),
        "robot": {
            "position": robot.get("position"),
            "position_at": robot.get("position_at"),
            "moving": view.robot_moving,
        },
        "jog": {"max_step_mm": settings.jog_max_step_mm, "speed_mm_s": settings.jog_speed_mm_s},
        "state": view.state.value,
    }


@router.get("/calibration/markers")
async def get_markers(request: Request) -> dict[str, Any]:
    """The marker layout in force, the draft being taught, and the robot's last known pose."""
    return layout_view(request.app.state.settings, _store(request), _cell(request))


def _refuse_unless_still(cell: Cell, what: str) -> None:
    view = cell.view
    if view.state is not State.IDLE:
        raise HTTPException(409, f"{what} is refused in {view.state.value}: the cell must be IDLE")
    if view.robot_moving:
        raise HTTPException(409, f"{what} is refused: the robot is still moving (home or a jog)")


@router.post(
    "/calibration/markers/draft/{marker}/teach", responses={**REFUSED, **audit.STORAGE_REFUSALS}
)
async def teach_marker(request: Request, marker: Marker) -> dict[str, Any]:
    """Record the tool's current x and y as marker `marker`'s position in the draft.

    Only in IDLE with the robot still (409 otherwise): the pose is read from the
    robot now, and refused if a move began while it was read. The tool's height
    is not recorded: the markers lie on the table plane.
    """
    cell, settings = _cell(request), request.app.state.settings
    what = f"teach marker {marker}"
    _refuse_unless_still(cell, what)
    moves = cell.view.robot_moves_started
    limit = settings.robot_communication_timeout
    try:
        pose = await read_pose_within(cell.devices.robot, limit)
    except Exception as exc:
        reason = f"no answer within {limit:g} s" if isinstance(exc, TimeoutError) else exc
        raise HTTPException(
            409, f"{what}: the robot's position could not be read ({reason})"
        ) from None
    _refuse_unless_still(cell, what)
    if cell.view.robot_moves_started != moves:
        raise HTTPException(409, f"{what} is refused: the robot moved while it was read")
    detail = f"marker {marker} taught at ({pose.x:.3f}, {pose.y:.3f}) mm (draft)"
    await audit.record_before_change(request, detail)
    store = _store(request)
    await audit.save(request, detail, lambda: store.set_marker(marker, pose.x, pose.y, "taught"))
    return layout_view(settings, store, cell)


@router.put("/calibration/markers/draft/{marker}", responses=audit.STORAGE_REFUSALS)
async def type_marker(request: Request, marker: Marker, body: MarkerPosition) -> dict[str, Any]:
    """Type marker `marker`'s position into the draft (a correction, or a measured value)."""
    detail = f"marker {marker} typed as ({body.x_mm:g}, {body.y_mm:g}) mm (draft)"
    await audit.record_before_change(request, detail)
    store = _store(request)
    await audit.save(
        request, detail, lambda: store.set_marker(marker, body.x_mm, body.y_mm, "typed")
    )
    return layout_view(request.app.state.settings, store, _cell(request))


@router.delete("/calibration/markers/draft", responses=audit.STORAGE_REFUSALS)
async def clear_draft(request: Request) -> dict[str, Any]:
    """Start the draft over; the layout in force is not touched."""
    await audit.record_before_change(request, "marker layout draft cleared")
    store = _store(request)
    await audit.save(request, "marker layout draft cleared", store.clear_draft)
    return layout_view(request.app.state.settings, store, _cell(request))


_MARKER_IN_MESSAGE = re.compile(r"\bmarkers? (\d)\b")


def _layout_errors(exc: ValidationError) -> list[LayoutProblem]:
    """The settings' other refusals of the layout as field errors."""
    return [_layout_problem(str(e["msg"]).removeprefix("Value error, ")) for e in exc.errors()]


def _layout_problem(message: str) -> LayoutProblem:
    """A layout problem as a field error naming its (first) marker, `markers.N`."""
    named = _MARKER_IN_MESSAGE.search(message)
    where = f"markers.{named.group(1)}" if named else "marker_positions_mm"
    return LayoutProblem(field=where, message=message, type="layout")


def _refused(request: Request, errors: list[LayoutProblem]) -> JSONResponse:
    """409: the draft, not the request, is what is wrong (the request has no body)."""
    summary = "; ".join(f"{e.field}: {e.message}" for e in errors)
    body = LayoutRefusal(detail=f"the draft layout cannot be applied: {summary}", errors=errors)
    request.state.audit_reason = body.detail
    return JSONResponse(body.model_dump(), status_code=409)


@router.post(
    "/calibration/markers/apply",
    response_model=None,
    responses={
        409: {
            "model": LayoutRefusal,
            "description": "not now (a robot calibration runs), or the draft lacks a marker "
            "or fails the layout check: each error's field names the marker (markers.N); "
            "nothing changed",
        },
        **audit.STORAGE_REFUSALS,
    },
)
async def apply_markers(request: Request) -> dict[str, Any] | JSONResponse:
    """Put the draft in force as marker_positions_mm, once all nine pass the layout check.

    409 naming each marker still missing, or each marker the check refuses (outside
    the workspace, overlapping, degenerate), as `errors[].field` `markers.N`;
    nothing changes then. Refused while a robot calibration runs (409). Audited
    with the old and new layout; kept in the data directory, so a restart keeps
    it in force.
    """
    cell, settings = _cell(request), request.app.state.settings
    store = _store(request)
    if cell.view.state is State.CALIBRATING_ROBOT:
        raise HTTPException(409, "apply is refused while the robot calibration runs")
    missing = store.missing()
    if missing:
        return _refused(
            request,
            [
                LayoutProblem(
                    field=f"markers.{i}",
                    message=f"marker {i} has no position in the draft yet: teach it or type it",
                    type="missing",
                )
                for i in missing
            ],
        )
    layout = store.draft_layout()
    problems = marker_layout_problems(
        layout, settings.workspace_min_mm, settings.workspace_max_mm, settings.marker_size_mm
    )
    if problems:  # each one, not the first the settings' check raises
        return _refused(request, [_layout_problem(problem) for problem in problems])
    try:
        changes = plan_change(settings, MarkerLayoutChange(marker_positions_mm=layout))
    except ValidationError as exc:
        return _refused(request, _layout_errors(exc))
    old = [list(p) for p in settings.marker_positions_mm]
    detail = f"marker_positions_mm: {old} -> {[list(p) for p in layout]} (taught layout applied)"
    await audit.record_before_change(request, detail)
    await audit.save(request, detail, lambda: store.record_applied(layout))
    if "marker_positions_mm" in changes:
        settings.marker_positions_mm = changes["marker_positions_mm"][1]
    return layout_view(settings, store, cell)

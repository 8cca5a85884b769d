"""Query routes: read-only views of the machine and the devices."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, FastAPI, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, JSONResponse

from server.api.analytics import TEXT_MAX_LENGTH, TEXT_PATTERN
from server.api.declared_query import DeclaredQueryRoute
from server.api.direct_json import DirectJsonRoute
from server.api.schemas import (
    FRAME_RETRY_AFTER_S,
    AllowedView,
    ErrorView,
    FramePendingView,
    HealthView,
    StateView,
    binary_body,
)
from server.api.watch import system_of
from server.bootstrap.cell import Cell
from server.commands.catalogue import may
from server.core.machine.transitions import Command, normalize_command
from server.core.operations.frames import Frame
from server.core.worker.view import CellView
from server.security.tokens import Principal

router = APIRouter(tags=["queries"], route_class=DeclaredQueryRoute)


def _cell(request: Request) -> Cell:
    return request.app.state.cell


def _view(request: Request) -> CellView:
    return request.app.state.cell.view


async def get_state(request: Request) -> dict:
    """The current state, the running operation and its progress, the fault if any.

    `may` is what the caller's token may do now: the commands the state allows
    (`available_commands`) that its role allows too (server/commands/catalogue.py).
    """
    snapshot = _view(request).snapshot()
    principal: Principal | None = getattr(request.state, "principal", None)
    if principal is not None:
        snapshot["may"] = may(principal.role, snapshot["available_commands"])
    return snapshot


def add_state_route(app: FastAPI) -> None:
    """GET /state on the app's own router, ahead of every included router.

    Why: it is the most polled route, and its cost should be the framework's
    floor (bench/rest_throughput.py). FastAPI matches an included router's
    routes through a layer of its own (the router is matched, then its routes
    again) that an app-level route skips; and `DirectJsonRoute` answers it
    without FastAPI's per-request machinery, with the same answer. Call it
    before including the routers: the router tries routes in order.
    """
    app.router.add_api_route(
        "/state",
        get_state,
        methods=["GET"],
        response_model=StateView,
        tags=["queries"],
        route_class_override=DirectJsonRoute,
    )


@router.get(
    "/operations/{name}/allowed",
    response_model=AllowedView,
    responses={404: {"model": ErrorView, "description": "no such operation"}},
)
async def is_allowed(request: Request, name: str) -> AllowedView:
    """Whether a command would be accepted in the current state, and why not."""
    canonical = normalize_command(name)
    if canonical is None:
        known = ", ".join(Command)
        raise HTTPException(404, f"unknown operation {name!r}; known operations: {known}")
    view = _view(request)
    allowed, reason = view.allowed(canonical)
    return AllowedView(operation=canonical, allowed=allowed, state=view.state.value, reason=reason)


@router.get("/health", response_model=HealthView)
async def get_health(request: Request) -> dict:
    """Each device's link, last round-trip and last error; the worker's and journal's figures."""
    return health_of(request.app)


def health_of(app: FastAPI) -> dict[str, Any]:
    """What GET /health answers (the MQTT link publishes the same, retained, on `health`)."""
    cell = app.state.cell
    health = {
        **cell.view.health(),
        "websocket_clients": app.state.ws_hub.client_count,
        "system": system_of(cell),
    }
    link = getattr(app.state, "mqtt", None)
    if link is not None:
        health["mqtt"] = link.health()
    return health


@router.get("/calibration")
async def get_calibration(request: Request) -> dict[str, Any]:
    """The current robot and camera calibrations: errors, when made, the matrices."""
    cell = _cell(request)
    assert cell.stores is not None
    return cell.stores.calibration.summary()


@router.get(
    "/calibration/image",
    response_class=FileResponse,
    responses={200: {"content": binary_body("image/png")}, 404: {"model": ErrorView}},
)
async def get_calibration_image(request: Request) -> FileResponse:
    """The annotated frame of the last robot calibration (markers, ids, residuals)."""
    cell = _cell(request)
    assert cell.stores is not None
    path = cell.stores.calibration.robot_image_path
    if not path.exists():
        raise HTTPException(404, "no robot calibration yet: run calibrate-robot")
    return FileResponse(path, media_type="image/png")


FRAME_HEADERS = {
    "X-Frame-Time": {
        "description": "when the camera delivered the frame (Unix seconds, UTC)",
        "schema": {"type": "string", "example": "1718000000.123"},
    },
    "X-Frame-Source": {
        "description": "the operation that captured it: trajectory, create_workpiece "
        "or calibrate_robot",
        "schema": {"type": "string", "example": "trajectory"},
    },
    "X-Frame-Run-Id": {
        "description": "the run of that operation (as in /trajectory, /operations, the logs)",
        "schema": {"type": "string"},
    },
}
NO_FRAME = (
    "no camera frame captured since the server started: start a run with contour matching, "
    "create a workpiece or calibrate the robot (each captures one)"
)


RunIdQuery = Annotated[
    str | None,
    Query(
        max_length=TEXT_MAX_LENGTH,
        pattern=TEXT_PATTERN,
        description="the frame of this run only (the run_id of POST /start's 202): 409 with "
        "Retry-After while that run is under way and has not captured it yet, 404 once it "
        "is not kept",
    ),
]


@router.get(
    "/camera/frame",
    response_class=Response,
    responses={
        200: {
            "content": binary_body("image/jpeg"),
            "description": "the latest frame, undistorted, as JPEG",
            "headers": FRAME_HEADERS,
        },
        404: {
            "model": ErrorView,
            "description": "no frame captured yet, or none of the run asked for is kept",
        },
        409: {
            "model": FramePendingView,
            "description": "the run asked for has not captured its frame yet: retry",
            "headers": {"Retry-After": {"schema": {"type": "integer", "example": 1}}},
        },
    },
)
async def get_camera_frame(request: Request, run_id: RunIdQuery = None) -> Response:
    """The latest frame an operation captured (undistorted, as measured on), as JPEG;
    with `run_id`, only that run's.

    Why `run_id`: right after POST /start the latest frame is still the previous run's;
    a script that asks for its own run's frame is told to wait (409) or that it will
    not come (404), never handed another run's picture.
    """
    view = _view(request)
    frame = view.latest_frame()
    if run_id is not None and (frame is None or frame.run_id != run_id):
        return _frame_not_kept(view, run_id, frame)
    if frame is None:
        raise HTTPException(404, NO_FRAME)
    body = await asyncio.to_thread(view.frame_jpeg, frame)
    headers = {
        "X-Frame-Time": f"{frame.taken_at:.3f}",
        "X-Frame-Source": frame.source,
        "X-Frame-Run-Id": frame.run_id,
        "Cache-Control": "no-store",  # the next capture replaces it under the same URL
    }
    return Response(body, media_type="image/jpeg", headers=headers)


def _frame_not_kept(view: CellView, run_id: str, latest: Frame | None) -> JSONResponse:
    """409 (retry) while `run_id` is under way without its frame; 404 once it is over."""
    if view.is_current_run(run_id):
        pending = FramePendingView(
            detail=f"run {run_id} has not captured its frame yet: retry after "
            f"{FRAME_RETRY_AFTER_S} s (a trajectory run without contour matching captures "
            "none)",
            run_id=run_id,
            retry_after=FRAME_RETRY_AFTER_S,
        )
        return JSONResponse(
            pending.model_dump(),
            status_code=409,
            headers={"Retry-After": str(FRAME_RETRY_AFTER_S)},
        )
    kept = (
        f"the latest is run {latest.run_id}'s ({latest.source})"
        if latest is not None
        else "none has been captured since the server started"
    )
    detail = (
        f"no frame of run {run_id} is kept: {kept}. Only the latest frame is kept, and a run "
        "captures one only when it looks at the table (contour matching, workpiece "
        "creation, robot calibration)"
    )
    return JSONResponse({"detail": detail}, status_code=404)


@router.get("/trajectory", responses={404: {"model": ErrorView}})
async def get_trajectory(request: Request) -> dict[str, Any]:
    """The planned path of the current or last run, with the waypoint reached."""
    trajectory = _view(request).trajectory()
    if trajectory is None:
        raise HTTPException(404, "no trajectory planned since the server started")
    return trajectory

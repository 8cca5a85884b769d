"""The camera set-up view over HTTP: its status (GET /camera/preview) and its stream
(WebSocket /camera/preview/ws), for the maintenance role.

Why a WebSocket and not MJPEG: a browser's <img> cannot send the bearer header, and a
token in an MJPEG URL would end up in proxy logs; the one-shot tickets of POST /ws-ticket
already solve this for /ws. The same connection also carries each frame's figures as
JSON, paired with the very frame they were measured on, and lets the server skip frames
for a slow client (it sends the newest when the last send is done).

Each frame is two messages: a text message, the figures (`"type": "frame"`), then a
binary message, the JPEG. As on /ws, a refused stream is accepted and closed at once with a
code and the reason, which a browser can read (an HTTP denial of the handshake it cannot;
and uvicorn logs an error after each one): 4429 too many bad tokens from the address,
4401 no valid ticket or token, 4403 not maintenance, 4409 the cell is not IDLE, 1013
camera_preview_clients reached. A stream ended
by the server: 4409 the cell left IDLE, 1011 the camera failed, 4401 the token was
revoked, 4001 the client fell behind (a send did not complete in SEND_TIMEOUT), 1012 the
server is stopping. GET /camera/preview says beforehand whether a stream may open.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

from fastapi import APIRouter, Request, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, Field

from server.api.access import websocket_lockout, websocket_principal
from server.api.declared_query import DeclaredQueryRoute
from server.security.tokens import Role
from server.views.camera_preview import (
    ALLOWED,
    CLOSE_CAMERA_BUSY,
    CLOSE_UNAUTHORIZED,
    CameraPreview,
    PreviewRefused,
    Watcher,
)

router = APIRouter(tags=["camera set-up"], route_class=DeclaredQueryRoute)
ws_router = APIRouter()

NEEDED = Role.MAINTENANCE
SEND_TIMEOUT = 5.0
CLOSE_SLOW = 4001


class PreviewStatus(BaseModel):
    """Whether the set-up view may open now, and the figures of its last frame."""

    allowed: bool = Field(description="a stream may open now")
    reason: str | None = Field(description="why not, when it may not")
    allowed_states: list[str] = Field(description="the states in which it runs")
    clients: int = Field(description="streams open now")
    max_clients: int = Field(description="camera_preview_clients")
    fps: float = Field(description="camera_preview_fps: frames a second at most")
    running: bool = Field(description="frames are being captured (someone watches)")
    last_frame: dict | None = Field(
        description="the figures of the last frame streamed since the server started "
        "(as each stream's text messages), or null"
    )


def _preview(connection: Request | WebSocket) -> CameraPreview:
    return connection.app.state.camera_preview


@router.get("/camera/preview", response_model=PreviewStatus)
async def get_preview_status(request: Request) -> PreviewStatus:
    """Whether the camera set-up view may open now (and why not), its limits, its last figures."""
    preview = _preview(request)
    settings = request.app.state.settings
    refused = preview.refusal()
    return PreviewStatus(
        allowed=refused is None,
        reason=None if refused is None else refused.reason,
        allowed_states=sorted(state.value for state in ALLOWED),
        clients=preview.clients,
        max_clients=settings.camera_preview_clients,
        fps=settings.camera_preview_fps,
        running=preview.running,
        last_frame=preview.last_figures,
    )


CLOSE_FORBIDDEN = 4403
CLOSE_TOO_MANY = 1013
# PreviewRefused's HTTP status → the close code that says the same on a WebSocket.
CLOSE_FOR_STATUS = {409: CLOSE_CAMERA_BUSY, 503: CLOSE_TOO_MANY}


async def _refuse(websocket: WebSocket, code: int, reason: str) -> None:
    await websocket.accept()
    await websocket.close(code, reason[:120])


@ws_router.websocket("/camera/preview/ws")
async def stream(websocket: WebSocket) -> None:
    """Annotated frames and their figures while the client watches (see the module)."""
    principal = websocket_principal(websocket)
    locked = websocket_lockout(websocket)
    if locked is not None:
        await _refuse(websocket, *locked)
        return
    if principal is None:
        await _refuse(
            websocket,
            CLOSE_UNAUTHORIZED,
            "unauthorized: use a ticket from POST /ws-ticket, or send a bearer token",
        )
        return
    if principal.role < NEEDED:
        await _refuse(
            websocket,
            CLOSE_FORBIDDEN,
            f"the set-up view needs the {NEEDED.label} role; this token is {principal.role.label}",
        )
        return
    preview = _preview(websocket)
    try:
        watcher = preview.watch(principal)
    except PreviewRefused as refused:
        await _refuse(websocket, CLOSE_FOR_STATUS[refused.status], refused.reason)
        return
    try:
        await websocket.accept()
        tasks: list[asyncio.Future[tuple[int, str] | None]] = [
            asyncio.create_task(_send_frames(websocket, watcher)),
            asyncio.create_task(_drain(websocket)),
        ]
        waiting: list[asyncio.Future[Any]] = [*tasks, watcher.ended]
        await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        close = watcher.ended.result() if watcher.ended.done() else _first_result(tasks)
        if close is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(SEND_TIMEOUT):
                    await websocket.close(close[0], close[1][:120])
    except WebSocketDisconnect:
        pass
    finally:
        preview.leave(watcher)


async def _send_frames(websocket: WebSocket, watcher: Watcher) -> tuple[int, str] | None:
    """The newest frame each time the last one is sent; None when the client is gone."""
    while True:
        frame = await watcher.next_frame()
        try:
            async with asyncio.timeout(SEND_TIMEOUT):
                await websocket.send_text(json.dumps(frame.figures))
                await websocket.send_bytes(frame.jpeg)
        except TimeoutError:
            return CLOSE_SLOW, "slow consumer: a frame was not taken in time"
        except (WebSocketDisconnect, RuntimeError, OSError):
            return None


def _first_result(tasks: list[asyncio.Future[tuple[int, str] | None]]) -> tuple[int, str] | None:
    """The close a finished sender asks for (None: the client went, or it drained)."""
    for task in tasks:
        if task.done() and not task.cancelled() and task.exception() is None:
            return task.result()
    return None


async def _drain(websocket: WebSocket) -> None:
    """Read (and ignore) what the client sends, to hear when it goes."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return

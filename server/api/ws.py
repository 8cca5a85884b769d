"""WebSocket /ws: a snapshot first, then every bus message, in order.

Each client is one bus subscription with a bounded buffer. A client that falls
behind (its buffer fills, or one send takes longer than SEND_TIMEOUT) is
closed with code 4001 and never delays the worker or the other clients.

Close codes (also in docs/api.md):
  1003  the client sent something that is not a valid JSON message
  1009  the client sent a message over the size limit (enforced by the server)
  1013  too many clients (max_broadcast_clients); try again later
  4001  slow consumer: the client fell behind and was dropped
  4401  unauthorized: no valid one-shot ticket (POST /ws-ticket) or bearer token
  1012  the server is restarting or shutting down (sent by uvicorn)

Client → server messages (JSON): `{"type": "subscribe", "types": [...]}`
limits the message types sent from then on (null for all; `seq` then has gaps
for the filtered types); `{"type": "ping"}` is answered with `{"type": "pong"}`.
Dead connections are found by protocol-level pings (ws_ping_interval).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections import OrderedDict
from typing import Any

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.api.auth import authenticate_websocket
from server.core.bus import BusMessage, SubscriptionClosed

log = logging.getLogger(__name__)
router = APIRouter()

MESSAGE_TYPES = ("state_changed", "progress", "error", "alert")
SEND_TIMEOUT = 5.0
SNAPSHOT_HISTORY = 20
ENCODED_CACHE = 64  # recent messages kept encoded; a client further behind re-encodes

CLOSE_INVALID = 1003
CLOSE_TOO_MANY = 1013
CLOSE_SLOW = 4001
CLOSE_UNAUTHORIZED = 4401


class ClientMessage(BaseModel):
    """What a client may send."""

    model_config = ConfigDict(extra="forbid")

    type: str = Field(pattern="^(subscribe|ping)$")
    types: list[str] | None = Field(None, max_length=len(MESSAGE_TYPES))


class WebSocketHub:
    """Counts clients, enforces max_broadcast_clients, and encodes each message once."""

    def __init__(self, max_clients: int, buffer: int) -> None:
        self.max_clients = max_clients
        self.buffer = buffer
        self.client_count = 0
        self._encoded: OrderedDict[int, str] = OrderedDict()

    def encode(self, message: BusMessage) -> str:
        """The message's JSON text, shared by every client (clients lag by a few at most)."""
        text = self._encoded.get(message.seq)
        if text is None:
            text = json.dumps(message.as_dict())
            self._encoded[message.seq] = text
            if len(self._encoded) > ENCODED_CACHE:
                self._encoded.popitem(last=False)
        return text


@router.websocket("/ws")
async def live(websocket: WebSocket) -> None:
    app = websocket.app
    hub: WebSocketHub = app.state.ws_hub
    worker = app.state.cell.worker
    principal = authenticate_websocket(websocket)
    await websocket.accept()
    if principal is None:
        await websocket.close(
            CLOSE_UNAUTHORIZED,
            "unauthorized: open /ws with a ticket from POST /ws-ticket, or send a bearer token",
        )
        return
    if hub.client_count >= hub.max_clients:
        await websocket.close(CLOSE_TOO_MANY, f"too many clients (max {hub.max_clients})")
        return
    hub.client_count += 1
    # Subscribe before taking the snapshot, so nothing falls between the two.
    subscription = worker.bus.subscribe(hub.buffer)
    try:
        snapshot: dict[str, Any] = {
            "type": "snapshot",
            "seq": worker.bus.last_seq,
            **worker.snapshot(),
            "context": {
                "operation_data": worker.ctx.operation_data,
                "error_message": worker.ctx.error_message,
                "operation_result": worker.ctx.operation_result,
            },
            "history": [r.as_dict() for r in list(worker.ctx.history)[-SNAPSHOT_HISTORY:]],
        }
        await websocket.send_json(snapshot)
        sender = asyncio.create_task(_send_loop(websocket, subscription, hub))
        receiver = asyncio.create_task(_receive_loop(websocket, subscription))
        done, pending = await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        close_code, reason = next(iter(done)).result()
        if close_code is not None:
            # Bounded: a client that stopped reading may never take the close frame,
            # and must not hold its place among max_broadcast_clients (or a shutdown)
            # until the keepalive notices; the keepalive still ends the connection.
            with contextlib.suppress(Exception):
                async with asyncio.timeout(SEND_TIMEOUT):
                    await websocket.close(close_code, reason)
    except WebSocketDisconnect:
        pass
    finally:
        subscription.close("client gone")
        hub.client_count -= 1


async def _send_loop(
    websocket: WebSocket, subscription: Any, hub: WebSocketHub
) -> tuple[int | None, str]:
    while True:
        try:
            message = await subscription.get()
        except SubscriptionClosed as closed:
            return CLOSE_SLOW, f"{closed.reason}: you fell behind; reconnect and resync"
        try:
            async with asyncio.timeout(SEND_TIMEOUT):  # no extra task per send, unlike wait_for
                await websocket.send_text(hub.encode(message))
        except TimeoutError:
            return CLOSE_SLOW, "slow consumer: a send did not complete in time"
        except (WebSocketDisconnect, RuntimeError, OSError):
            return None, ""


async def _receive_loop(websocket: WebSocket, subscription: Any) -> tuple[int | None, str]:
    while True:
        try:
            raw = await websocket.receive_text()
        except WebSocketDisconnect:
            return None, ""
        except (KeyError, RuntimeError):  # a binary frame, or the socket went away
            return CLOSE_INVALID, "send JSON text messages only"
        try:
            message = ClientMessage.model_validate_json(raw)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "message"
            return CLOSE_INVALID, f"invalid message ({where}: {first['msg']})"[:120]
        if message.type == "ping":
            await websocket.send_json({"type": "pong"})
            continue
        unknown = set(message.types or ()) - set(MESSAGE_TYPES)
        if unknown:
            return CLOSE_INVALID, f"unknown message types: {', '.join(sorted(unknown))}"[:120]
        subscription.set_types(message.types)
        await websocket.send_json({"type": "subscribed", "types": message.types})

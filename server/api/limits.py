"""A request body larger than max_request_bytes is refused with 413 before it is read whole.

The HTTP door (server/api/door.py) asks `bounded` after the access check and the
stop lane, so a stop never meets it: the lane reads a stop's body itself, up to the
same limit, and stops the cell even when the body is too large
(server/api/stop_lane.py). A declared Content-Length over the limit is refused at
once; a streamed body (Transfer-Encoding) is counted as it arrives by a
`StreamedBody`, and its answer replaced by the 413 once it goes over.
"""

from __future__ import annotations

import json
from typing import Any

from starlette.types import Message, Receive, Scope, Send


def bounded(
    scope: Scope, receive: Receive, send: Send, max_bytes: int
) -> tuple[Receive, Send] | None:
    """The `receive` and `send` to hand the request on with; None if its declared
    Content-Length is over `max_bytes` (then the caller answers `refuse`).

    A request without Transfer-Encoding keeps its own: its body is bounded by the
    Content-Length just checked (the HTTP server reads no more), or it has none, as on
    every GET. A streamed one is counted (`StreamedBody`).
    """
    declared = None
    chunked = False
    for name, value in scope.get("headers") or ():
        if name == b"content-length":
            declared = value
        elif name == b"transfer-encoding":
            chunked = True
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        return None
    if not chunked:
        return receive, send
    streamed = StreamedBody(scope, receive, send, max_bytes)
    return streamed.receive, streamed.send


class StreamedBody:
    """A streamed body counted as it arrives: past the limit the app gets an empty,
    final chunk, and its answer is replaced by the 413."""

    def __init__(self, scope: Scope, receive: Receive, send: Send, max_bytes: int) -> None:
        self._scope = scope
        self._receive = receive
        self._send = send
        self._max_bytes = max_bytes
        self._received = 0
        self._too_large = False
        self._refused = False

    async def receive(self) -> Message:
        if self._too_large:
            return {"type": "http.request", "body": b"", "more_body": False}
        message = await self._receive()
        if message["type"] == "http.request":
            self._received += len(message.get("body", b""))
            if self._received > self._max_bytes:
                self._too_large = True
                return {"type": "http.request", "body": b"", "more_body": False}
        return message

    async def send(self, message: Message) -> None:
        if not self._too_large:
            await self._send(message)
        elif not self._refused:
            self._refused = True
            await refuse(self._scope, self._send, self._max_bytes)


async def refuse(scope: Scope, send: Send, max_bytes: int) -> None:
    """The 413, its reason left for the refusal's audit row."""
    detail = f"request body over {max_bytes} bytes"
    scope.setdefault("state", {})["audit_reason"] = detail
    body: dict[str, Any] = {"detail": detail}
    payload = json.dumps(body).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 413,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(payload)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": payload})

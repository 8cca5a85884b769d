"""A request body larger than max_request_bytes is refused with 413 before it is read whole.

It sits inside the access gate and the stop lane (server/bootstrap/app.py), so a
stop never meets it: the lane reads a stop's body itself, up to the same limit,
and stops the cell even when the body is too large (server/api/stop_lane.py).
"""

from __future__ import annotations

import json
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send


def _body_headers(scope: Scope) -> tuple[bytes | None, bool]:
    """The request's Content-Length, and whether it names a Transfer-Encoding."""
    declared = None
    chunked = False
    for name, value in scope.get("headers") or ():
        if name == b"content-length":
            declared = value
        elif name == b"transfer-encoding":
            chunked = True
    return declared, chunked


class BodySizeLimit:
    """ASGI middleware: checks Content-Length, and counts a streamed body as it arrives.

    A request without Transfer-Encoding passes with no wrapper: its body is
    bounded by the Content-Length already checked (or it has none).
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared, chunked = _body_headers(scope)
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await self._refuse(scope, send)
            return
        if not chunked:
            # No Transfer-Encoding: the body is at most the Content-Length just checked
            # (the HTTP server reads no more), or none at all, as on every GET.
            await self.app(scope, receive, send)
            return
        received = 0
        too_large = False

        async def counting_receive() -> Message:
            # Past the limit the app gets an empty, final chunk; its answer is replaced below.
            nonlocal received, too_large
            if too_large:
                return {"type": "http.request", "body": b"", "more_body": False}
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    too_large = True
                    return {"type": "http.request", "body": b"", "more_body": False}
            return message

        refused = False

        async def guarded_send(message: Message) -> None:
            nonlocal refused
            if not too_large:
                await send(message)
            elif not refused:
                refused = True
                await self._refuse(scope, send)

        await self.app(scope, counting_receive, guarded_send)

    async def _refuse(self, scope: Scope, send: Send) -> None:
        detail = f"request body over {self.max_bytes} bytes"
        scope.setdefault("state", {})["audit_reason"] = detail  # the refusal's audit row
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

"""A request body larger than max_request_bytes is refused with 413 before it is read whole.

Except on a stop route: a stop is never refused over its body. There the body
is dropped instead (the route sees none) and the route is told why, so it can
make the stop and answer 413 beside it.
"""

from __future__ import annotations

import json
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api.stop_lane import is_stop


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
        if is_stop(scope):
            await self.app(scope, self._dropping_oversized(scope, receive), send)
            return
        declared, chunked = _body_headers(scope)
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await self._refuse(send)
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
                await self._refuse(send)

        await self.app(scope, counting_receive, guarded_send)

    def _dropping_oversized(self, scope: Scope, receive: Receive) -> Receive:
        """The whole body, or none with `body_dropped` in the request's state if over the limit.

        Read whole before the route sees any of it (bounded by the limit), so the
        route gets either valid bytes or nothing, never a truncated document.
        """
        delivered = False

        def dropped() -> Message:
            why = f"request body over {self.max_bytes} bytes, not read"
            scope.setdefault("state", {})["body_dropped"] = why
            return {"type": "http.request", "body": b"", "more_body": False}

        async def receive_whole() -> Message:
            nonlocal delivered
            if delivered:
                return await receive()
            delivered = True
            declared = dict(scope.get("headers") or []).get(b"content-length")
            if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
                return dropped()
            chunks: list[bytes] = []
            size = 0
            while True:
                message = await receive()
                if message["type"] != "http.request":
                    return message
                chunk = message.get("body", b"")
                size += len(chunk)
                if size > self.max_bytes:
                    return dropped()
                chunks.append(chunk)
                if not message.get("more_body", False):
                    return {"type": "http.request", "body": b"".join(chunks), "more_body": False}

        return receive_whole

    async def _refuse(self, send: Send) -> None:
        body: dict[str, Any] = {"detail": f"request body over {self.max_bytes} bytes"}
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

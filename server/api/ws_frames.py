"""One WebSocket frame for every client: built once per message, written to each socket.

Why: with a thousand /ws clients, sending each message through Starlette's and
uvicorn's send path once per client (a state check, an awaited flow-control
event, a timeout handle, the websockets protocol building the very same frame
again) costs tens of µs of server CPU per client and message before the socket
write, more than the fan-out to 1000 clients' 50 ms budget allows
(docs/benchmarks.md). A server-to-client text frame carries no mask
(RFC 6455 §5.1) and, with permessage-deflate declined (server/__main__.py),
no per-connection compression: its bytes are the same for every client, so
they are built once (`text_frame`) and handed to each connection's transport
as they are (`FrameWriter`).

The writer speaks to uvicorn's websockets-sansio connection (what
`--ws auto` picks) and only when writing cannot wait or go wrong: the
handshake is done, the connection open, no close sent, no extension
negotiated, and the transport not paused by flow control. Otherwise it says
so (`write` returns False) and the caller uses the ordinary awaited send,
whose timeout then guards a client that stopped reading. Under any other
server implementation `FrameWriter.of` gives None and every send is the
ordinary one.
"""

from __future__ import annotations

import asyncio

from starlette.websockets import WebSocket
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.frames import Frame, Opcode
from websockets.protocol import State


def text_frame(text: str) -> bytes:
    """The unmasked, uncompressed, unfragmented text frame of `text`, as sent on the wire."""
    return Frame(Opcode.TEXT, text.encode()).serialize(mask=False, extensions=[])


class FrameWriter:
    """Writes prepared frames straight to one connection's transport, when it is safe to."""

    __slots__ = ("_protocol",)

    def __init__(self, protocol: WebSocketsSansIOProtocol) -> None:
        self._protocol = protocol

    @classmethod
    def of(cls, websocket: WebSocket) -> FrameWriter | None:
        """A writer for an accepted connection served by uvicorn's websockets-sansio, else None."""
        # The server's receive reaches the app as it is (the middlewares wrap only an
        # HTTP request's), and is a method of the connection's protocol.
        protocol = getattr(websocket._receive, "__self__", None)
        if not isinstance(protocol, WebSocketsSansIOProtocol):
            return None
        if not isinstance(protocol.writable, asyncio.Event):
            return None
        if protocol.conn.extensions:
            return None  # a negotiated extension (compression) rewrites every frame
        return cls(protocol)

    def write(self, frame: bytes) -> bool:
        """Write `frame` now (True), or False: the caller must send it the ordinary way."""
        protocol = self._protocol
        if (
            protocol.close_sent
            or protocol.disconnected
            or not protocol.writable.is_set()
            or protocol.conn.state is not State.OPEN
            or protocol.transport.is_closing()
        ):
            return False
        protocol.transport.write(frame)
        return True

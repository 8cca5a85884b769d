"""The Python clients and a kept-alive connection the server closes.

The server closes a connection idle for `http_keepalive_timeout` (5 s by default,
0.5 s at the least). A client that keeps idle connections as long or longer sends
its next request, now and then, just as the server closes the connection: the
request fails with no answer (httpx's ReadError or RemoteProtocolError), though the
server is up. `Peer` below does what the server does in that moment, every time: it
answers the first request on a connection and closes the connection when the
second arrives, unanswered.

What the clients do about it: a read (GET) is sent again once on a new connection,
as reading twice changes nothing; a command (POST) or a change (PATCH) is not, as the
server may have taken it, and the client says it got no answer. So that commands do not meet the
race at the server's default timeout, an idle connection is let go well before it
(`KEEPALIVE_EXPIRY_S`).
"""

from __future__ import annotations

import asyncio
import socket
import socketserver
import threading
import time
from collections.abc import Iterator

import pytest

from clients.client import AsyncCellClient, CellClient, Unreachable
from clients.client.config import KEEPALIVE_EXPIRY_S
from server.settings.model import Settings

ANSWER = b'{"state": "IDLE"}'
ACCEPTED = b'{"accepted": true, "command": "reset", "state": "IDLE"}'


class _ClosingAtTheSecondRequest(socketserver.StreamRequestHandler):
    """Answer one request per connection; close the connection when the next one comes."""

    def handle(self) -> None:
        peer: Peer = self.server  # type: ignore[assignment]
        for answered in (False, True):
            request_line = self.rfile.readline()
            if not request_line:
                return
            length = 0
            while (line := self.rfile.readline()) not in (b"\r\n", b""):
                name, _, value = line.decode("latin-1").partition(":")
                if name.strip().lower() == "content-length":
                    length = int(value)
            self.rfile.read(length)
            peer.requests.append((request_line.split()[0].decode(), answered))
            if answered:
                # The request came as the server let the connection go: no answer, and
                # a reset rather than an orderly close, as a kernel answers data sent
                # to a socket already closed.
                self.connection.setsockopt(
                    socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00"
                )
                return
            body = ACCEPTED if request_line.startswith(b"POST") else ANSWER
            status = b"202 Accepted" if request_line.startswith(b"POST") else b"200 OK"
            self.wfile.write(
                b"HTTP/1.1 " + status + b"\r\ncontent-type: application/json\r\n"
                b"content-length: " + str(len(body)).encode() + b"\r\n\r\n" + body
            )
            self.wfile.flush()


class Peer(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _ClosingAtTheSecondRequest)
        self.requests: list[tuple[str, bool]] = []  # (method, the connection's second)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}"


@pytest.fixture
def peer() -> Iterator[Peer]:
    server = Peer()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


def test_a_read_on_a_connection_the_server_closed_is_sent_again_once(peer: Peer) -> None:
    with CellClient(peer.url, "token") as client:
        assert client.state() == {"state": "IDLE"}
        assert client.state() == {"state": "IDLE"}
    # The second went on the kept-alive connection, unanswered; then on a new one.
    assert peer.requests == [("GET", False), ("GET", True), ("GET", False)]


async def test_the_async_client_sends_a_read_again_once_too(peer: Peer) -> None:
    async with AsyncCellClient(peer.url, "token") as client:
        assert await client.state() == {"state": "IDLE"}
        assert await client.state() == {"state": "IDLE"}
    assert peer.requests == [("GET", False), ("GET", True), ("GET", False)]


def test_a_command_without_an_answer_is_not_sent_again(peer: Peer) -> None:
    with CellClient(peer.url, "token") as client:
        assert client.reset().accepted
        with pytest.raises(Unreachable, match="cannot reach"):
            client.reset()
    assert peer.requests == [("POST", False), ("POST", True)]


async def test_the_async_client_does_not_send_a_command_again(peer: Peer) -> None:
    async with AsyncCellClient(peer.url, "token") as client:
        assert (await client.reset()).accepted
        with pytest.raises(Unreachable, match="cannot reach"):
            await client.reset()
    assert peer.requests == [("POST", False), ("POST", True)]


def test_a_change_without_an_answer_is_not_sent_again(peer: Peer) -> None:
    with CellClient(peer.url, "token") as client:
        client.change_settings(log_retention_days=30)
        with pytest.raises(Unreachable, match="cannot reach"):
            client.change_settings(log_retention_days=30)
    assert peer.requests == [("PATCH", False), ("PATCH", True)]


def test_a_connection_idle_past_the_clients_expiry_is_not_used_again(peer: Peer) -> None:
    """A server configured below the default timeout: the client is given a shorter expiry."""
    with CellClient(peer.url, "token", keepalive_expiry=0.05) as client:
        assert client.reset().accepted
        time.sleep(0.2)
        assert client.reset().accepted
    assert peer.requests == [("POST", False), ("POST", False)]


async def test_the_async_client_lets_an_idle_connection_go_too(peer: Peer) -> None:
    async with AsyncCellClient(peer.url, "token", keepalive_expiry=0.05) as client:
        assert (await client.reset()).accepted
        await asyncio.sleep(0.2)
        assert (await client.reset()).accepted
    assert peer.requests == [("POST", False), ("POST", False)]


def test_the_clients_let_a_connection_go_well_before_the_server_does() -> None:
    server_closes_after = Settings.model_fields["http_keepalive_timeout"].default
    assert server_closes_after / 2 >= KEEPALIVE_EXPIRY_S

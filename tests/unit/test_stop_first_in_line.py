"""A stop read by the HTTP protocol goes first in the loop's line; a command read
before it still counts as asked before it (server/api/connection_guard.py,
server/api/door.py: `on_headers`).

The protocol is uvicorn's httptools protocol as the server runs it, on the test's
own loop, fed bytes as a socket would; the app behind it only records what it is
handed, so the order of the loop's work is what is under test.
"""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from uvicorn.config import Config
from uvicorn.server import ServerState

from server.api.connection_guard import ConnectionLimits, guarded_http_protocol
from server.api.door import ASKED_AT_ESTOPS

HEAD = "Host: cell\r\nContent-Type: application/json\r\nContent-Length: 2\r\n\r\n{}"


class RecordingApp:
    """An ASGI app of a started cell: notes each request's path as its task first runs,
    and counts a stop as the stop lane would, at once."""

    def __init__(self) -> None:
        self.stops = 0
        self.state = SimpleNamespace(cell=SimpleNamespace(started=True, stops_now=self.count))
        self.seen: list[str] = []
        self.asked_at: dict[str, int | None] = {}

    def count(self) -> int:
        return self.stops

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        self.seen.append(scope["path"])
        self.asked_at[scope["path"]] = scope.get("state", {}).get(ASKED_AT_ESTOPS)
        if scope["path"] == "/estop":
            self.stops += 1
        await send({"type": "http.response.start", "status": 202, "headers": []})
        await send({"type": "http.response.body", "body": b"{}"})


class Transport(asyncio.Transport):
    def __init__(self) -> None:
        super().__init__()
        self.closing = False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return {"sockname": ("127.0.0.1", 8000), "peername": ("127.0.0.1", 50000)}.get(
            name, default
        )

    def write(self, data: Any) -> None:
        pass

    def is_closing(self) -> bool:
        return self.closing

    def close(self) -> None:
        self.closing = True

    def pause_reading(self) -> None:
        pass

    def resume_reading(self) -> None:
        pass


def connections(app: RecordingApp, count: int) -> list[Any]:
    """`count` connections of one server, as uvicorn opens them."""
    protocol = guarded_http_protocol(
        ConnectionLimits(header_timeout=10, max_connections=100, max_per_address=100)
    )
    config = Config(app, http=protocol, proxy_headers=False, log_level="warning")
    config.load()
    state = ServerState()
    opened = []
    for _ in range(count):
        connection = protocol(config=config, server_state=state, app_state={})  # type: ignore[call-arg]
        connection.connection_made(Transport())
        opened.append(connection)
    return opened


async def test_a_stop_runs_before_the_work_queued_ahead_of_it() -> None:
    app = RecordingApp()
    flood, hmi = connections(app, 2)
    asyncio.get_running_loop().call_soon(app.seen.append, "queued before")
    flood.data_received(f"POST /pause HTTP/1.1\r\n{HEAD}".encode())
    hmi.data_received(f"POST /estop HTTP/1.1\r\n{HEAD}".encode())
    await asyncio.sleep(0)
    # The stop first, ahead of the loop's work and of the pause read before it.
    assert app.seen == ["/estop", "queued before", "/pause"]


async def test_other_requests_keep_their_place_in_the_line() -> None:
    app = RecordingApp()
    (connection,) = connections(app, 1)
    asyncio.get_running_loop().call_soon(app.seen.append, "queued before")
    connection.data_received(b"POST /pause HTTP/1.1\r\n" + HEAD.encode())
    await asyncio.sleep(0)
    assert app.seen == ["queued before", "/pause"]
    assert app.asked_at["/pause"] == 0  # noted as it was read


async def test_a_command_read_before_a_stop_that_overtakes_it_is_asked_before_it() -> None:
    app = RecordingApp()
    operator, hmi = connections(app, 2)
    operator.data_received(f"POST /reset HTTP/1.1\r\n{HEAD}".encode())
    hmi.data_received(f"POST /estop HTTP/1.1\r\n{HEAD}".encode())
    await asyncio.sleep(0)
    assert app.seen == ["/estop", "/reset"]
    # The reset found no stop as it was read, though the stop was made before it ran:
    # the decision refuses it (a stop made after it was asked).
    assert app.asked_at["/reset"] == 0 and app.stops == 1

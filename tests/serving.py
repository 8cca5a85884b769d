"""Run the real app under uvicorn on a free loopback port, inside the test's loop; or,
for tests of the API's contract rather than of the socket, call it in process."""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import uvicorn

from server.__main__ import uvicorn_options
from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell


def admin_headers(data_path: Path) -> dict[str, str]:
    """The Authorization header of the admin token the server created on first start."""
    token = (Path(data_path) / "admin.token").read_text(encoding="utf-8").strip()
    return {"Authorization": f"Bearer {token}"}


def admin_client(port: int, data_path: Path) -> httpx.Client:
    """A client of `python -m server` on loopback `port`, holding the admin token of `data_path`."""
    return httpx.Client(
        base_url=f"http://127.0.0.1:{port}", timeout=30, headers=admin_headers(data_path)
    )


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


# Ports above the privileged range that Chromium refuses to open (net::ERR_UNSAFE_PORT),
# whatever serves them: a dashboard on one cannot be loaded by the browser tests.
BROWSER_REFUSED_PORTS = frozenset(
    {1719, 1720, 1723, 2049, 3659, 4045, 4190, 5060, 5061, 6000, 6566}
    | set(range(6665, 6670))
    | {6679, 6697, 10080}
)


def free_port() -> int:
    """A loopback port free now, chosen below the kernel's ephemeral range and never
    one a browser refuses (`BROWSER_REFUSED_PORTS`).

    A port the kernel hands out for bind(0) is also one it hands out as the local end
    of any outgoing connection: while a test starts a server on it (a subprocess that
    commissions its cell first), another test's client can take it. Below the range,
    only another test choosing the same port at random can."""
    low, _ = _ephemeral_range()
    floor = 10000 if low > 12000 else 1024
    ceiling = low - 16  # room for a few ports numbered after it
    for _ in range(200 if ceiling - floor >= 1000 else 0):  # no room below: as the kernel says
        port = random.randrange(floor, ceiling)
        if port in BROWSER_REFUSED_PORTS:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextlib.asynccontextmanager
async def serve(
    cell: Cell, port: int | None = None, **uvicorn_overrides: Any
) -> AsyncIterator[str]:
    """Serve `cell` over HTTP as `python -m server` does (unless overridden); yields the URL
    (https when the cell's settings name a certificate).

    `port`: a free one unless given (a restarted server answers at the same address)."""
    port = port or free_port()
    config = uvicorn.Config(
        create_app(cell=cell),
        host="127.0.0.1",
        port=port,
        log_level="warning",
        lifespan="on",
        **{**uvicorn_options(cell.settings), **uvicorn_overrides},
    )
    server = uvicorn.Server(config)
    server.install_signal_handlers = lambda: None  # type: ignore[method-assign]
    task = asyncio.create_task(server.serve())
    # Start-up commissions a fresh simulated cell (CPU-bound): a bound, not a performance
    # assertion, so generous for a machine busy with other work.
    async with asyncio.timeout(120):
        while not server.started:
            if task.done():
                task.result()
            await asyncio.sleep(0.01)
    scheme = "https" if cell.settings.tls_cert_file else "http"
    try:
        yield f"{scheme}://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        await asyncio.wait_for(task, 20)


# The peer address an in-process request comes from: loopback, as a local client's.
IN_PROCESS_PEER = ("127.0.0.1", 50000)


@contextlib.asynccontextmanager
async def in_process(cell: Cell, *, timeout: float = 10) -> AsyncIterator[httpx.AsyncClient]:
    """The real app on `cell`, called in this loop through httpx's ASGI transport, with
    the admin token: no socket, no uvicorn.

    For what a test asks of the API itself (routes, validation, answers, refusals): the
    same app, middleware, lifespan and cell as `serve` runs. What lives in uvicorn and
    its protocol (server/api/connection_guard.py: connection and header limits, idle
    keep-alives; TLS; the WebSocket) is not here: tests of those use `serve`. An error
    in the app is answered 500, as the server would, instead of raised into the test.
    """
    app = create_app(cell=cell)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False, client=IN_PROCESS_PEER)
        async with httpx.AsyncClient(
            transport=transport,
            base_url="http://127.0.0.1",
            timeout=timeout,
            headers=admin_headers(cell.settings.data_path),
        ) as client:
            yield client

"""Run the real app under uvicorn on a free loopback port, inside the test's loop."""

from __future__ import annotations

import asyncio
import contextlib
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


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


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

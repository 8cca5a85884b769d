"""The first stop after a start is as ready as any later one (server/api/route_warmup.py).

FastAPI prepares a route the first time a request is matched against it; the first
POST /estop of a fresh server prepared every route ahead of /estop before its handler
commanded the devices (10 ms of a stop that otherwise takes half a millisecond in the
server, bench.estop_latency's first trial). Start-up now does it. Seen here by
counting the routes FastAPI prepares while the first stop is on its way: none.
"""

from __future__ import annotations

import asyncio
from typing import Any

import fastapi.routing
import httpx
import pytest

from server.api.route_warmup import prepare_routes
from server.bootstrap.app import create_app
from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve


async def test_the_first_stop_after_a_start_prepares_no_route(
    fast_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    prepared: list[str] = []
    prepare = fastapi.routing._populate_api_route_state

    def counted(route: Any, path: str, *args: Any, **kwargs: Any) -> Any:
        prepared.append(path)
        return prepare(route, path, *args, **kwargs)

    monkeypatch.setattr(fastapi.routing, "_populate_api_route_state", counted)
    cell = Cell(fast_settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with serve(cell) as url, httpx.AsyncClient(base_url=url, timeout=10) as client:
        assert "/estop" in prepared, "start-up prepared the stop's route"
        prepared.clear()
        answer = await client.post("/estop", headers=admin_headers(fast_settings.data_path))
        assert answer.status_code == 202
        assert prepared == []
        # Nothing of the start-up's own request is on record: no audit row for it.
        audit = await client.get("/audit", headers=admin_headers(fast_settings.data_path))
        assert "/-/prepare-routes" not in audit.text


async def test_routes_are_prepared_one_at_a_time_between_other_work(
    fast_settings: Settings,
) -> None:
    """The preparation runs beside the cell's start (its devices connecting): it lets the
    event loop go between two of the router's entries, never holding it for all of them."""
    cell = Cell(fast_settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    app = create_app(fast_settings, cell=cell)
    turns = 0
    preparing = True

    async def other_work() -> None:
        nonlocal turns
        while preparing:
            turns += 1
            await asyncio.sleep(0)

    beside = asyncio.create_task(other_work())
    await prepare_routes(app)
    preparing = False
    await beside
    assert turns >= len(app.router.routes) - 1

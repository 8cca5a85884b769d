"""The first stop after a start is as ready as any later one (server/api/route_warmup.py).

FastAPI prepares a route the first time a request is matched against it; the first
POST /estop of a fresh server prepared every route ahead of /estop before its handler
commanded the devices (10 ms of a stop that otherwise takes half a millisecond in the
server, bench.estop_latency's first trial). Start-up now does it. Seen here by
counting the routes FastAPI prepares while the first stop is on its way: none.
"""

from __future__ import annotations

from typing import Any

import fastapi.routing
import httpx
import pytest

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

"""Resuming /ws after a reconnect: `after_seq` and `boot`, over real sockets.

The server runs in this test's loop on in-process fakes, so the test can publish
on the bus directly (as the worker does) at exactly the moments that matter:
while no client is connected, or all the while a client reconnects.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import urlencode

import httpx
import pytest
import websockets
from websockets.asyncio.client import ClientConnection, connect

from server.bootstrap.cell import Cell
from server.core.infra.bus import REPLAY_HISTORY
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import START, demo_stores, is_waypoint
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve


class Api:
    """The served cell: its HTTP client, its bus, and /ws with any query."""

    def __init__(self, http: httpx.AsyncClient, cell: Cell, url: str) -> None:
        self.http = http
        self.cell = cell
        self.bus = cell.bus
        self._ws_url = url.replace("http", "ws", 1) + "/ws"

    def connect(self, **query: Any) -> connect:
        url = f"{self._ws_url}?{urlencode(query)}" if query else self._ws_url
        return connect(
            url, additional_headers={"Authorization": self.http.headers["authorization"]}
        )

    def publish(self, count: int, start: int = 0) -> None:
        for index in range(count):
            self.bus.publish("progress", {"waypoint": start + index})

    async def wait_idle(self) -> None:
        async with asyncio.timeout(20):
            while (await self.http.get("/state")).json()["state"] != "IDLE":
                await asyncio.sleep(0.01)


@pytest.fixture
async def api(fast_settings: Settings) -> AsyncIterator[Api]:
    devices = CellDevices(FakeRobot(speed_factor=5), FakeGlue(), FakeCamera())
    demo_stores(fast_settings.data_path)
    cell = Cell(fast_settings, devices=devices)
    async with (
        serve(cell) as url,
        httpx.AsyncClient(
            base_url=url, timeout=10, headers=admin_headers(fast_settings.data_path)
        ) as http,
    ):
        served = Api(http, cell, url)
        await served.wait_idle()
        yield served


async def receive(ws: ClientConnection) -> dict[str, Any]:
    return json.loads(await asyncio.wait_for(ws.recv(), 10))


async def first_snapshot(api: Api) -> dict[str, Any]:
    async with api.connect() as ws:
        snapshot = await receive(ws)
    assert snapshot["type"] == "snapshot" and snapshot["boot"] == api.bus.boot
    assert "replayed" not in snapshot and "missed" not in snapshot
    return snapshot


async def no_clients(api: Api) -> None:
    async with asyncio.timeout(5):
        while (await api.http.get("/health")).json()["websocket_clients"] != 0:
            await asyncio.sleep(0.01)


async def closed_with(ws: ClientConnection) -> tuple[int, str]:
    with pytest.raises(websockets.ConnectionClosed) as closed:
        await asyncio.wait_for(ws.recv(), 5)
    assert closed.value.rcvd is not None
    return closed.value.rcvd.code, closed.value.rcvd.reason


async def test_a_resume_replays_what_went_by_then_goes_live(api: Api) -> None:
    seen = await first_snapshot(api)
    # While nobody is connected: a whole run (transitions and progress) and a burst.
    assert (await api.http.post("/start", json=START)).status_code == 202
    await api.wait_idle()
    api.publish(5, start=100)
    async with api.connect(after_seq=seen["seq"], boot=seen["boot"]) as ws:
        snapshot = await receive(ws)
        assert snapshot["type"] == "snapshot" and snapshot["state"] == "IDLE"
        assert snapshot["replayed"] == snapshot["seq"] - seen["seq"] > 5
        assert "missed" not in snapshot
        replayed = [await receive(ws) for _ in range(snapshot["replayed"])]
        api.publish(1, start=1000)
        live = await receive(ws)
    assert [m["seq"] for m in replayed] == list(range(seen["seq"] + 1, snapshot["seq"] + 1))
    states = [m["new_state"] for m in replayed if m["type"] == "state_changed"]
    assert states == ["EXECUTING_TRAJECTORY", "IDLE"]
    waypoints = [m["waypoint"] for m in replayed if is_waypoint(m)]
    assert waypoints == [*range(1, 8), *range(100, 105)]
    assert live["seq"] == snapshot["seq"] + 1 and live["waypoint"] == 1000


async def test_resuming_at_the_last_seq_replays_nothing(api: Api) -> None:
    seen = await first_snapshot(api)
    async with api.connect(after_seq=seen["seq"], boot=seen["boot"]) as ws:
        snapshot = await receive(ws)
        assert snapshot["replayed"] == 0 and snapshot["seq"] == seen["seq"]
        api.publish(1)
        assert (await receive(ws))["seq"] == seen["seq"] + 1


async def test_replay_and_live_meet_without_gap_or_duplicate_while_publishing(api: Api) -> None:
    """Messages published all the while the client connects: the seam must be exact."""
    seen = await first_snapshot(api)
    stop = asyncio.Event()

    async def publisher() -> None:
        index = 0
        while not stop.is_set():
            api.publish(3, start=index)
            index += 3
            await asyncio.sleep(0.001)  # well within the ring while a client connects

    task = asyncio.create_task(publisher())
    try:
        for _ in range(5):  # each resume lands at a different point of the stream
            async with api.connect(after_seq=seen["seq"], boot=seen["boot"]) as ws:
                snapshot = await receive(ws)
                assert snapshot["replayed"] == snapshot["seq"] - seen["seq"]
                seqs = [(await receive(ws))["seq"] for _ in range(snapshot["replayed"] + 40)]
            assert seqs == list(range(seen["seq"] + 1, seen["seq"] + 1 + len(seqs)))
            seen = {"seq": seqs[-1], "boot": seen["boot"]}
    finally:
        stop.set()
        await task


async def test_the_types_filter_applies_to_the_replay(api: Api) -> None:
    seen = await first_snapshot(api)
    assert (await api.http.post("/start", json=START)).status_code == 202
    await api.wait_idle()
    async with api.connect(after_seq=seen["seq"], boot=seen["boot"], types="state_changed") as ws:
        snapshot = await receive(ws)
        assert snapshot["replayed"] == 2  # of the run's messages, only its two transitions
        replayed = [await receive(ws) for _ in range(2)]
        api.publish(1)  # filtered out live too
        api.bus.publish("state_changed", {"new_state": "IDLE"})
        live = await receive(ws)
    assert [m["new_state"] for m in replayed] == ["EXECUTING_TRAJECTORY", "IDLE"]
    assert all(m["type"] == "state_changed" for m in replayed)
    assert live["type"] == "state_changed" and live["seq"] == snapshot["seq"] + 2


async def test_an_after_seq_older_than_the_ring_is_missed_not_replayed(api: Api) -> None:
    seen = await first_snapshot(api)
    api.publish(REPLAY_HISTORY + 10)
    async with api.connect(after_seq=seen["seq"], boot=seen["boot"]) as ws:
        snapshot = await receive(ws)
        assert snapshot["missed"] == snapshot["seq"] - seen["seq"] >= REPLAY_HISTORY + 10
        assert "replayed" not in snapshot
        api.publish(1, start=1000)
        live = await receive(ws)  # no replay came in between
    assert live["seq"] == snapshot["seq"] + 1 and live["waypoint"] == 1000


async def test_another_boot_is_missed_not_replayed(api: Api) -> None:
    """A seq from another server process (a restart) must not be taken for ours."""
    seen = await first_snapshot(api)
    api.publish(3)
    async with api.connect(after_seq=seen["seq"], boot="0123456789abcdef") as ws:
        snapshot = await receive(ws)
        assert snapshot["missed"] == snapshot["seq"] > 0  # everything this server published
        assert "replayed" not in snapshot and snapshot["boot"] == seen["boot"]
        api.publish(1, start=1000)
        assert (await receive(ws))["seq"] == snapshot["seq"] + 1


@pytest.mark.parametrize(
    ("query", "says"),
    [
        ({"after_seq": "-1", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "abc", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "1.5", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "+3", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "²", "boot": "b"}, "non-negative integer"),
        ({"after_seq": "9" * 40, "boot": "b"}, "non-negative integer"),
        ({"after_seq": "3"}, "after_seq and boot go together"),
        ({"boot": "b"}, "after_seq and boot go together"),
        ({"after_seq": "3", "boot": "b" * 65}, "boot must be"),
        ({"types": "state_changed,telemetry"}, "unknown message types: telemetry"),
    ],
)
async def test_a_bad_resume_query_is_closed_with_1003_saying_why(
    api: Api, query: dict[str, str], says: str
) -> None:
    async with api.connect(**query) as ws:
        code, reason = await closed_with(ws)
    assert code == 1003 and says in reason
    health = (await api.http.get("/health")).json()
    assert health["websocket_clients"] == 0  # refused before it took a place


async def test_an_after_seq_this_server_never_reached_is_refused(api: Api) -> None:
    seen = await first_snapshot(api)
    await no_clients(api)
    subscribers = api.bus.subscriber_count
    async with api.connect(after_seq=seen["seq"] + 5, boot=seen["boot"]) as ws:
        code, reason = await closed_with(ws)
    assert code == 1003 and "beyond this server's last seq" in reason
    await no_clients(api)
    assert api.bus.subscriber_count == subscribers  # the refused one's is gone

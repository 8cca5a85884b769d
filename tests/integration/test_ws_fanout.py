"""/ws fan-out over real sockets: every client gets its messages once, in order, by either road.

The hub has two roads to a client's socket (server/api/ws.py): the bus hands a
message straight to the socket while the client's send task waits, and the
task sends it the ordinary way otherwise (a paused transport, a replay, a
backlog). These tests publish on the bus directly, as the worker does, in
bursts and single messages, to many clients with different filters, and one
client that stops reading; what each client receives is checked message by
message. No timing: every wait is for a message or a close.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import random
import socket
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlencode, urlsplit

import httpx
import pytest
import websockets
from websockets.asyncio.client import ClientConnection, connect

from server.api import ws as ws_module
from server.bootstrap.cell import Cell
from server.core.infra.bus import Bus, BusMessage, DirectConsumer
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve

WS_BUFFER = 16  # ws_client_buffer: a client that stops reading is dropped soon
ROOMY_BUFFER = 256  # the default: bursts of up to a hundred drop no one
MARK = "fanout_test"  # the key that tells this test's messages from the cell's own
SETTLE_S = 30  # bound on a wait for a message or a close; never reached when sound
# A client on a poor link (as in tests/reliability/test_ws_churn.py): the smallest
# receive window and segments, so a few hundred kilobytes fill the TCP buffers.
SLOW_RCVBUF = 1024
SLOW_MSS = 88
PAD = "x" * 2000  # a large progress message: the slow client's buffers fill sooner


@dataclass
class Served:
    cell: Cell
    bus: Bus
    url: str
    headers: dict[str, str]


@pytest.fixture
async def served(fast_settings: Settings, request: pytest.FixtureRequest) -> AsyncIterator[Served]:
    """The cell on fakes, served; ws_client_buffer is WS_BUFFER unless parametrized."""
    settings = fast_settings.model_copy(
        update={
            "ws_client_buffer": getattr(request, "param", WS_BUFFER),
            "max_broadcast_clients": 100,
            "max_broadcast_clients_per_token": 100,
        }
    )
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(), FakeGlue(), FakeCamera()))
    async with serve(cell) as url:
        headers = admin_headers(settings.data_path)
        async with httpx.AsyncClient(base_url=url, headers=headers, timeout=10) as http:
            async with asyncio.timeout(SETTLE_S):
                while (await http.get("/state")).json()["state"] != "IDLE":
                    await asyncio.sleep(0.01)
        yield Served(cell, cell.bus, url.replace("http", "ws", 1) + "/ws", headers)


@dataclass
class Handed:
    """How many messages the hub's direct consumer took, and how many it could not."""

    count: int = 0
    refused: int = 0


@pytest.fixture
def handed(monkeypatch: pytest.MonkeyPatch) -> Handed:
    counter = Handed()
    direct_sender = ws_module._direct_sender

    def counting(*args: Any) -> DirectConsumer:
        consumer = direct_sender(*args)

        def counted(message: BusMessage) -> bool:
            taken = consumer(message)
            counter.count += taken
            counter.refused += not taken
            return taken

        return counted

    monkeypatch.setattr(ws_module, "_direct_sender", counting)
    return counter


@dataclass
class Reader:
    """One /ws client reading everything it is sent, in the background."""

    ws: ClientConnection
    received: list[dict[str, Any]] = field(default_factory=list)
    arrived: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None

    @classmethod
    async def open(cls, served: Served, subscribe: list[str] | None = None, **query: str) -> Reader:
        url = f"{served.url}?{urlencode(query)}" if query else served.url
        ws = await connect(url, additional_headers=served.headers)
        assert json.loads(await ws.recv())["type"] == "snapshot"
        if subscribe is not None:
            await ws.send(json.dumps({"type": "subscribe", "types": subscribe}))
            assert json.loads(await ws.recv())["type"] == "subscribed"
        reader = cls(ws)
        reader.task = asyncio.create_task(reader._read())
        return reader

    async def _read(self) -> None:
        async for raw in self.ws:
            self.received.append(json.loads(raw))
            self.arrived.set()

    def marked(self) -> list[tuple[str, int]]:
        return [(m["type"], m[MARK]) for m in self.received if MARK in m]

    async def wait_for(self, done: Callable[[Reader], bool]) -> None:
        async with asyncio.timeout(SETTLE_S):
            while not done(self):
                assert self.task is not None
                if self.task.done():  # closed by the server: say how, at once
                    raise AssertionError(f"the client ended: {self.task.exception()!r}")
                self.arrived.clear()
                arrival = asyncio.ensure_future(self.arrived.wait())
                await asyncio.wait({self.task, arrival}, return_when=asyncio.FIRST_COMPLETED)
                arrival.cancel()

    async def close(self) -> None:
        await self.ws.close()
        if self.task is not None:
            await self.task


async def slow_client(served: Served) -> ClientConnection:
    """A progress client that reads its snapshot, then nothing: a small window and segments."""
    return await poor_link_client(served)


async def poor_link_client(served: Served) -> ClientConnection:
    """A progress client on a poor link: read nothing and its server's transport pauses soon."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SLOW_RCVBUF)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, SLOW_MSS)
    sock.setblocking(False)
    address = urlsplit(served.url)
    await asyncio.get_running_loop().sock_connect(sock, (address.hostname, address.port))
    # max_queue=1: the client library stops reading the socket after one message;
    # no compression (the server declines it anyway).
    ws = await connect(
        f"{served.url}?types=progress",
        additional_headers=served.headers,
        sock=sock,
        max_queue=1,
        compression=None,
    )
    assert json.loads(await ws.recv())["type"] == "snapshot"
    return ws


async def read_until_closed(ws: ClientConnection) -> tuple[list[dict[str, Any]], int, str]:
    """Everything the server still sends, then its close code and reason."""
    received = []
    try:
        async with asyncio.timeout(SETTLE_S):
            while True:
                received.append(json.loads(await ws.recv()))
    except websockets.ConnectionClosed as closed:
        assert closed.rcvd is not None, f"closed without a close frame: {closed}"
        return received, closed.rcvd.code, closed.rcvd.reason


def numbered_in_order(reader: Reader) -> bool:
    seqs = [m["seq"] for m in reader.received if "seq" in m]
    return all(a < b for a, b in itertools.pairwise(seqs))


@pytest.mark.parametrize("served", [ROOMY_BUFFER], indirect=True)
async def test_every_client_gets_its_messages_once_and_in_order_through_bursts(
    served: Served, handed: Handed
) -> None:
    groups: dict[str, tuple[set[str], list[Reader]]] = {
        "everything": ({"state_changed", "progress", "error"}, []),
        "states, from the query": ({"state_changed"}, []),
        "progress, from a subscribe message": ({"progress"}, []),
        "samples and states": ({"device", "state_changed"}, []),
    }
    for _ in range(6):
        groups["everything"][1].append(await Reader.open(served))
        groups["states, from the query"][1].append(await Reader.open(served, types="state_changed"))
        groups["progress, from a subscribe message"][1].append(
            await Reader.open(served, subscribe=["progress"])
        )
        groups["samples and states"][1].append(
            await Reader.open(served, types="device,state_changed")
        )
    readers = [reader for _, members in groups.values() for reader in members]

    rng = random.Random(17)
    published: list[tuple[str, int]] = []
    for index in range(1200):
        kind = rng.choice(["progress", "progress", "state_changed", "error", "device"])
        if kind == "device":
            served.bus.publish_sample("device", {MARK: index})
        else:
            served.bus.publish(kind, {MARK: index})
        published.append((kind, index))
        if rng.random() < 0.3:  # a burst ends: some turns of the loop pass
            for _ in range(rng.randrange(4)):
                await asyncio.sleep(0)
        if index % 100 == 99:  # keep within the clients' buffers: no one is dropped here
            for types, members in groups.values():
                expected = sum(kind in types for kind, _ in published)
                for reader in members:
                    await reader.wait_for(lambda r, n=expected: len(r.marked()) >= n)

    for types, members in groups.values():
        expected = [(kind, index) for kind, index in published if kind in types]
        count = len(expected)
        for reader in members:
            await reader.wait_for(lambda r, n=count: len(r.marked()) >= n)
            assert reader.marked() == expected
            assert numbered_in_order(reader)
    assert handed.count > 0  # the direct road was taken
    for reader in readers:
        await reader.close()


async def test_a_client_that_stops_reading_is_dropped_and_the_others_get_everything(
    served: Served, handed: Handed
) -> None:
    good = [await Reader.open(served, types="progress") for _ in range(4)]
    slow = await slow_client(served)
    subscribers = served.bus.subscriber_count
    published: list[int] = []
    # Each message is waited for at every good client before the next, so only the
    # slow one falls behind; bounded in case it never is.
    while served.bus.subscriber_count == subscribers and len(published) < 5000:
        published.append(served.bus.publish("progress", {MARK: len(published), "pad": PAD}).seq)
        count = len(published)
        for reader in good:
            await reader.wait_for(lambda r, n=count: len(r.marked()) >= n)
    assert served.bus.subscriber_count == subscribers - 1, "the slow client was never dropped"

    received, code, reason = await read_until_closed(slow)
    assert code == 4001 and "slow consumer" in reason, (code, reason)
    seqs = [m["seq"] for m in received]
    assert seqs == published[: len(seqs)]  # a prefix of the stream: no gap, no repeat
    for reader in good:
        assert [m["seq"] for m in reader.received] == published
    assert handed.count > 0 and handed.refused > 0  # it fell behind once its socket was full
    for reader in good:
        await reader.close()
    # The others go on after the drop.
    last = await Reader.open(served)
    served.bus.publish("progress", {MARK: -1})
    await last.wait_for(lambda r: r.marked() == [("progress", -1)])
    await last.close()


@pytest.mark.parametrize("served", [1024], indirect=True)
async def test_a_client_that_stalls_then_catches_up_gets_everything_in_order(
    served: Served, handed: Handed
) -> None:
    """Its transport pauses and resumes while messages keep coming: both roads, in turn.

    Each round: 100 messages while it reads nothing (its buffers fill, the transport
    pauses, its task takes over), 50 more while it reads again (the transport
    resumes as new messages arrive), then it catches up (the direct road reopens).
    """
    good = await Reader.open(served, types="progress")
    stalling = await poor_link_client(served)
    reading = asyncio.Event()
    received: list[int] = []
    caught_up = asyncio.Event()
    published = 0

    async def read() -> None:
        while True:
            await reading.wait()
            received.append(json.loads(await stalling.recv())[MARK])
            if len(received) == published:
                caught_up.set()

    async def publish() -> None:
        nonlocal published
        served.bus.publish("progress", {MARK: published, "pad": PAD * 4})
        published += 1
        await good.wait_for(lambda r, n=published: len(r.marked()) >= n)

    reader = asyncio.create_task(read())
    rounds = 8
    for _ in range(rounds):
        reading.clear()
        for _ in range(100):
            await publish()
        reading.set()
        for _ in range(50):
            await publish()
        caught_up.clear()
        async with asyncio.timeout(SETTLE_S):
            while len(received) < published:
                assert not reader.done(), reader
                await asyncio.wait(
                    {reader, asyncio.ensure_future(caught_up.wait())},
                    return_when=asyncio.FIRST_COMPLETED,
                )
    reader.cancel()
    assert received == list(range(published))
    assert handed.count > 0 and handed.refused > 0  # both roads were taken
    await stalling.close()
    await good.close()

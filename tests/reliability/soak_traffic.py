"""The soak's crowd: WebSocket clients coming and going all through the run, and
bursts of concurrent operator commands.

Why beside the soak's cycles rather than in tests of their own: test_ws_churn
and test_storm prove each once, on a cell doing nothing else. In a plant the
live view is opened and closed all day while the cell runs, faults and resets,
and operators' commands arrive together; a leak or a race between them shows
only when they meet, over a long time.

The churning clients do what a dashboard does: ask for a one-shot ticket
(POST /ws-ticket), open /ws with it, read the snapshot and whatever follows for
a moment, and leave, politely or by dropping the connection. A refusal the API
documents (1013 too many clients, 4001 slow consumer, 503 for a ticket) is
counted; anything else a client meets is a failure, reported with what it was.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import ssl
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import websockets
from websockets.asyncio.client import ClientConnection

from tests.reliability.test_storm import MIX

CHURNERS = 3  # WebSocket clients at any moment, each coming and going
READ_S = 1.0  # a client reads for up to this long before it leaves
PAUSE_S = 0.3  # and waits up to this long before it comes back
ABRUPT_SHARE = 0.3  # clients that leave without a close handshake
DOCUMENTED_CLOSES = {1013, 4001}  # too many clients; slow consumer
STORM_CLIENTS = 8  # clients of a command burst, all at once
STORM_COMMANDS = 10  # commands each of them sends, one after another
SETTLE_S = 60.0  # bound on a connection or an answer: never reached when sound

Hook = Callable[[httpx.Response], Awaitable[None]]
Record = Callable[[str, float, float], None]  # kind, when (monotonic), seconds
# One TLS context for every client the soak opens (they speak plain HTTP on loopback
# anyway): httpx builds a fresh one per client by default, loading the CA bundle each
# time, which over thousands of clients would be the soak's own memory growth.
_TLS = ssl.create_default_context()


@dataclass
class ChurnCounts:
    connections: int = 0
    messages: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:  # dataclasses.asdict would garble the Counter
        return {**vars(self), "refused": dict(self.refused), "failures": list(self.failures)}


@dataclass
class StormCounts:
    bursts: int = 0
    commands: int = 0
    answers: Counter[int] = field(default_factory=Counter)

    def as_dict(self) -> dict[str, Any]:
        return {**vars(self), "answers": dict(self.answers)}


def client(base_url: str, headers: dict[str, str], hook: Hook) -> httpx.AsyncClient:
    """An HTTP client whose every answer the soak's verdict sees (5xx are judged)."""
    return httpx.AsyncClient(
        base_url=base_url,
        headers=headers,
        timeout=SETTLE_S,
        verify=_TLS,
        event_hooks={"response": [hook]},
    )


class WsChurn:
    """`CHURNERS` clients coming and going until stopped; `pause` makes them all leave."""

    def __init__(
        self, base_url: str, headers: dict[str, str], rng: random.Random, hook: Hook
    ) -> None:
        self.base_url = base_url
        self.ws_url = base_url.replace("http://", "ws://", 1) + "/ws"
        self.headers = headers
        self.hook = hook
        self.counts = ChurnCounts()
        self._seeds = [rng.randrange(2**32) for _ in range(CHURNERS)]
        self._running = asyncio.Event()
        self._stopping = False
        self._away = CHURNERS  # churners with no client open (HTTP or WebSocket)
        self._tasks: list[asyncio.Task[None]] = []

    def start(self) -> None:
        self._running.set()
        self._tasks = [asyncio.create_task(self._churner(seed)) for seed in self._seeds]

    async def pause(self) -> None:
        """Every churner finishes its visit, closes its clients and waits."""
        self._running.clear()
        async with asyncio.timeout(SETTLE_S):
            while self._away < CHURNERS:
                await asyncio.sleep(0.01)

    def resume(self) -> None:
        self._running.set()

    async def stop(self) -> None:
        self._stopping = True
        await self.pause()
        self._running.set()  # let the parked churners see they are done
        await asyncio.gather(*self._tasks)

    async def _churner(self, seed: int) -> None:
        rng = random.Random(seed)
        while True:
            await self._running.wait()
            if self._stopping:
                return
            self._away -= 1
            try:
                async with client(self.base_url, self.headers, self.hook) as http:
                    while self._running.is_set():
                        await self._visit(http, rng)
                        await asyncio.sleep(rng.uniform(0, PAUSE_S))
            except Exception as exc:  # a failure is the soak's to report, not to die of
                self.counts.failures.append(f"churner: {exc!r}")
            finally:
                self._away += 1

    async def _visit(self, http: httpx.AsyncClient, rng: random.Random) -> None:
        """One dashboard's visit: a ticket, the snapshot, a moment of reading, gone."""
        answer = await http.post("/ws-ticket")
        if answer.status_code != 200:
            self.counts.refused[f"ticket {answer.status_code}"] += 1
            return
        url = f"{self.ws_url}?ticket={answer.json()['ticket']}"
        try:
            ws = await websockets.connect(url, ping_interval=None, open_timeout=SETTLE_S)
        except websockets.InvalidStatus as refused:
            status = refused.response.status_code
            self.counts.refused[f"handshake {status}"] += 1
            if status >= 500 and status != 503:
                self.counts.failures.append(f"handshake answered {status}")
            return
        except (OSError, TimeoutError, websockets.WebSocketException) as exc:
            self.counts.failures.append(f"connect: {exc!r}")
            return
        self.counts.connections += 1
        try:
            await self._read(ws, rng)
        finally:
            with contextlib.suppress(websockets.WebSocketException, OSError):
                if rng.random() < ABRUPT_SHARE:
                    ws.transport.abort()  # gone without a close handshake
                    await ws.wait_closed()
                else:
                    await ws.close()

    async def _read(self, ws: ClientConnection, rng: random.Random) -> None:
        try:
            async with asyncio.timeout(SETTLE_S):
                first = json.loads(await ws.recv())
            if first.get("type") != "snapshot":
                self.counts.failures.append(f"first message not a snapshot: {first}")
            self.counts.messages += 1
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(rng.uniform(0, READ_S)):
                    while True:
                        await ws.recv()
                        self.counts.messages += 1
        except websockets.ConnectionClosed as closed:
            code = closed.rcvd.code if closed.rcvd is not None else None
            if code in DOCUMENTED_CLOSES:
                self.counts.refused[f"close {code}"] += 1
            else:
                self.counts.failures.append(f"closed by the server: {closed}")
        except TimeoutError:
            self.counts.failures.append("no snapshot within the bound")


async def command_burst(
    base_url: str,
    headers: dict[str, str],
    rng: random.Random,
    hook: Hook,
    record: Record,
    counts: StormCounts,
) -> set[str]:
    """`STORM_CLIENTS` clients at once, each sending `STORM_COMMANDS` commands from the
    storm test's mix; the event ids the server answered for (202 or 409)."""
    answered: set[str] = set()
    names = list(MIX)
    weights = [weight for weight, _ in MIX.values()]

    async def one_client(seed: int) -> None:
        own = random.Random(seed)
        async with client(base_url, headers, hook) as http:
            for _ in range(STORM_COMMANDS):
                command = own.choices(names, weights)[0]
                sent = time.monotonic()
                response = await http.post(f"/{command}", json=MIX[command][1])
                record("POST command", sent, time.monotonic() - sent)
                counts.commands += 1
                counts.answers[response.status_code] += 1
                body: Any = response.json() if response.status_code in (202, 409) else {}
                if isinstance(body, dict) and body.get("event_id"):
                    answered.add(body["event_id"])
                if response.status_code == 503:  # back off a little, as a client should
                    await asyncio.sleep(own.uniform(0, 0.05))

    await asyncio.gather(*(one_client(rng.randrange(2**32)) for _ in range(STORM_CLIENTS)))
    counts.bursts += 1
    return answered

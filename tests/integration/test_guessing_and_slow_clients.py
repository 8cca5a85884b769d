"""Guessing is slowed, refusals don't fill the journal, slow and idle clients are closed.

Against the real app served by uvicorn as `python -m
server` serves it (tests/serving.py), on real sockets: a flood of wrong tokens
from one address, sockets that dribble a header line at a time, sockets that
never send a byte, and more connections than the server holds. The bounds
waited for are the settings each test sets (and a generous margin over them):
no wall-clock threshold of their own.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import httpx
import pytest
import websockets

from server.bootstrap.cell import Cell
from server.core.worker.devices import CellDevices
from server.settings.model import Settings
from tests.conftest import demo_stores
from tests.fakes import FakeCamera, FakeGlue, FakeRobot
from tests.serving import admin_headers, serve

ATTACKER = "127.0.0.2"  # loopback is a /8 on Linux: a second client address on one host
OTHER = "127.0.0.3"
WRONG = {"Authorization": "Bearer gc_00000000_wrongwrongwrongwrong"}


@contextlib.asynccontextmanager
async def served(settings: Settings) -> AsyncIterator[str]:
    """The app on fakes, served as `python -m server` serves it; yields the URL."""
    demo_stores(settings.data_path)
    cell = Cell(settings, devices=CellDevices(FakeRobot(50), FakeGlue(), FakeCamera()))
    async with serve(cell) as url:
        yield url


def client_from(url: str, address: str, **kwargs: object) -> httpx.AsyncClient:
    """An HTTP client whose connections come from `address`."""
    transport = httpx.AsyncHTTPTransport(local_address=address)
    return httpx.AsyncClient(base_url=url, transport=transport, timeout=30, **kwargs)  # type: ignore[arg-type]


async def audit_rows(url: str, admin: dict[str, str], **filters: str) -> list[dict]:
    async with client_from(url, "127.0.0.1", headers=admin) as admin_client:
        answer = await admin_client.get("/audit", params={"limit": 10_000, **filters})
        assert answer.status_code == 200, answer.text
        return answer.json()["audit"]


async def test_a_flood_of_wrong_tokens_is_throttled_and_folded_in_the_audit(fast_settings) -> None:
    """3000 wrong tokens from one address were all 401, none 429, and wrote 3003 audit rows."""
    settings = fast_settings.model_copy(
        update={"auth_failure_limit": 20, "auth_failure_window": 60, "auth_lockout_s": 60}
    )
    flood = 3000
    async with served(settings) as url:
        admin = admin_headers(settings.data_path)
        statuses: list[int] = []
        retry_after: set[str | None] = set()
        async with client_from(url, ATTACKER, headers=WRONG) as attacker:

            async def guess(count: int) -> None:
                for _ in range(count):
                    answer = await attacker.get("/state")
                    statuses.append(answer.status_code)
                    if answer.status_code == 429:
                        retry_after.add(answer.headers.get("retry-after"))

            await asyncio.gather(*(guess(flood // 10) for _ in range(10)))
            assert len(statuses) == flood
            assert statuses.count(401) == 20, "the first auth_failure_limit are 401"
            assert statuses.count(429) == flood - 20
            assert retry_after and all(r is not None and 0 < int(r) <= 60 for r in retry_after)
            # Locked out: even the right token from the attacker's address waits...
            locked = await attacker.get("/state", headers=admin)
            assert locked.status_code == 429
            # ...but never the e-stop, with the right token, from the same address.
            stop = await attacker.post("/estop", headers=admin, json={"reason": "door"})
            assert stop.status_code == 202, stop.text
            # A wrong token on the e-stop is a 401, never a 429.
            assert (await attacker.post("/estop")).status_code == 401
        # The right token from another address works all along.
        async with client_from(url, OTHER, headers=admin) as other:
            assert (await other.get("/state")).status_code == 200
        rows = await audit_rows(url, admin, principal="anonymous")
        mine = [r for r in rows if r["address"] == ATTACKER and r["action"] == "GET /state"]
        assert sum(r["count"] for r in mine) == flood + 1, mine[:5]  # and the right token's 429
        assert len(mine) <= 4, f"{len(mine)} rows for {flood} refusals"
        assert {r["outcome"] for r in mine} == {"refused (401)", "refused (429)"}


async def test_a_websocket_with_bad_tickets_is_throttled_too(fast_settings) -> None:
    settings = fast_settings.model_copy(update={"auth_failure_limit": 3})
    async with served(settings) as url:
        admin = admin_headers(settings.data_path)
        ws_url = url.replace("http", "ws") + "/ws"
        codes = []
        for attempt in range(5):
            async with websockets.connect(f"{ws_url}?ticket=forged{attempt}") as forged:
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    await asyncio.wait_for(forged.recv(), 10)
                codes.append(closed.value.rcvd.code if closed.value.rcvd else None)
        assert codes == [4401, 4401, 4401, 4429, 4429]
        # A locked-out address is refused on HTTP as well, the e-stop excepted.
        async with client_from(url, "127.0.0.1", headers=admin) as client:
            assert (await client.get("/state")).status_code == 429
            assert (await client.post("/estop")).status_code == 202


async def test_identical_refusals_within_the_window_are_one_row_with_a_count(
    fast_settings,
) -> None:
    """No lockout here (a high limit): the folding alone keeps the journal small."""
    settings = fast_settings.model_copy(update={"auth_failure_limit": 10_000})
    async with served(settings) as url:
        admin = admin_headers(settings.data_path)
        async with client_from(url, ATTACKER) as anonymous:
            for _ in range(50):
                assert (await anonymous.post("/start")).status_code == 401
            assert (await anonymous.post("/pause")).status_code == 401
        rows = await audit_rows(url, admin, principal="anonymous")
        starts = [r for r in rows if r["action"] == "POST /start"]
        assert [r["count"] for r in starts] == [49, 1]  # newest first: the fold, then the first
        assert [r["count"] for r in rows if r["action"] == "POST /pause"] == [1]


async def dribble(address: str, port: int, every: float, stop: asyncio.Event) -> None:
    """A slow client: one header line every `every` seconds, until the server closes it."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(address, 0))
    try:
        writer.write(b"GET /state HTTP/1.1\r\nHost: cell\r\n")
        await writer.drain()
        line = 0
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                if await asyncio.wait_for(reader.read(1024), every) == b"":
                    return  # closed by the server
                return  # an answer (a 408): closed next
            line += 1
            writer.write(b"X-Slow-%d: still coming\r\n" % line)
            await writer.drain()
    except (ConnectionError, OSError):
        return
    finally:
        writer.close()


def port_of(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


async def test_slow_clients_are_closed_once_the_header_timeout_passes(fast_settings) -> None:
    """Sockets sending one header line every few seconds stayed open for good."""
    settings = fast_settings.model_copy(update={"http_header_timeout": 1.0})
    async with served(settings) as url:
        stop = asyncio.Event()
        slow = [asyncio.create_task(dribble(ATTACKER, port_of(url), 0.3, stop)) for _ in range(30)]
        try:
            # Closed by the server: well within 30 × the timeout (it was never, before).
            _, pending = await asyncio.wait(slow, timeout=30)
            assert not pending, f"{len(pending)} of 30 slow clients still open"
        finally:
            stop.set()
            await asyncio.gather(*slow, return_exceptions=True)


async def test_silent_and_idle_keep_alive_connections_are_closed(fast_settings) -> None:
    settings = fast_settings.model_copy(
        update={"http_header_timeout": 1.0, "http_keepalive_timeout": 1.0}
    )
    async with served(settings) as url:
        port = port_of(url)
        silent_reader, silent = await asyncio.open_connection("127.0.0.1", port)
        idle_reader, idle = await asyncio.open_connection("127.0.0.1", port)
        idle.write(b"GET /health HTTP/1.1\r\nHost: cell\r\n\r\n")
        await idle.drain()
        assert (await idle_reader.readuntil(b"\r\n\r\n")).startswith(b"HTTP/1.1 200")
        try:
            async with asyncio.timeout(30):
                while await silent_reader.read(1024):
                    pass
                while await idle_reader.read(1024):  # the rest of the answer, then the end
                    pass
        finally:
            silent.close()
            idle.close()


async def open_slowly(address: str, port: int) -> tuple[asyncio.StreamReader, asyncio.Task]:
    """A connection that sends part of a request and waits; its task ends when it is closed."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(address, 0))
    writer.write(b"GET /state HTTP/1.1\r\n")
    await writer.drain()

    async def until_closed() -> None:
        try:
            while await reader.read(1024):
                pass
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()

    return reader, asyncio.create_task(until_closed())


async def wait_until_open_at_most(tasks: list[asyncio.Task], most: int) -> None:
    async with asyncio.timeout(30):
        while sum(not t.done() for t in tasks) > most:
            await asyncio.sleep(0.05)


async def test_connections_are_bounded_per_address_and_in_all_and_the_estop_gets_in(
    fast_settings,
) -> None:
    """More slow connections than the server holds: the oldest waiting ones make room."""
    settings = fast_settings.model_copy(
        update={
            "http_header_timeout": 300,  # the bound, not the timeout, closes them here
            "http_max_connections": 16,
            "http_max_connections_per_address": 6,
        }
    )
    async with served(settings) as url:
        port = port_of(url)
        admin = admin_headers(settings.data_path)
        tasks: list[asyncio.Task] = []
        try:
            for _ in range(20):  # one address: held to its share
                tasks.append((await open_slowly(ATTACKER, port))[1])
            await wait_until_open_at_most(tasks, 6)
            for n in range(30):  # five more addresses, each within its share: the cap in all
                tasks.append((await open_slowly(f"127.0.1.{n % 5 + 1}", port))[1])
            await wait_until_open_at_most(tasks, 16)
            # The e-stop, from an address already at its share and with the server full.
            async with client_from(url, ATTACKER, headers=admin) as operator:
                stop = await operator.post("/estop", json={"reason": "under attack"})
                assert stop.status_code == 202, stop.text
            async with client_from(url, OTHER, headers=admin) as other:
                assert (await other.get("/state")).json()["state"] == "ERROR"
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

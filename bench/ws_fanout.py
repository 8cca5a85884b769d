"""WebSocket fan-out: how long a transition takes to reach each of N live clients.

An HMI, a line display and a supervisor's laptop all watch /ws; a transition
is only useful to them if it arrives at once, in order, and never silently
goes missing. This measures that for N = 10, 100 and 1000 clients.

How:
- The server is the production entry point, `python -m server`, in its own
  process (so its event loop is not the clients' loop), simulated devices,
  a fresh data directory, and max_broadcast_clients raised through
  GLUE_APP_MAX_BROADCAST_CLIENTS so that 1000+ clients are allowed (and
  max_broadcast_clients_per_token with it: every client uses one token). Every
  other setting is the default, including INFO logging of each transition.
- The clients are `websockets` connections in this process's loop (uvloop
  when installed), authenticated with the admin bearer token. Like browsers,
  they offer permessage-deflate unless --no-compression (the server declines
  it: see server/__main__.py). Each one subscribes to
  `state_changed` only ({"type": "subscribe", "types": ["state_changed"]}) and
  waits for the server's acknowledgement before the run starts.
- Transitions: POST /estop then POST /reset, alternating (IDLE → ERROR →
  IDLE). After each command the driver waits until every still-open client
  has the transition (or 10 s) before the next: this measures the fan-out of
  one transition, not a backlog of many.
- Latency of one delivery = the client's time.time() when `recv()` returns the
  message minus the message's own `time` field (stamped by the server when it
  published the transition; same machine, same clock). p50/p99/max are over
  every (client, transition) pair; `everyone_p99_ms` is the p99, over
  transitions, of the time until the *last* client had it.
- Delivery: a client is `complete` when it received exactly the transitions
  the driver caused (the event ids from the command answers), in that order,
  with strictly increasing seq (seq has gaps, for the filtered-out types, so
  the event ids are what proves nothing is missing). A client the server
  closed with 4001 (slow consumer, with a reason) counts as `dropped_told`;
  any other incomplete client counts as `missing`. Target at 1000 clients:
  p99 under 50 ms and no missing client.

What limits the measurement: the machine has few cores, and the clients
share them with the server: a receipt is stamped when this process's loop gets
to it, so with 1000 clients the figure includes the clients' own time to read
up to 999 other sockets first (client CPU seconds are reported beside the
server's). The clients' garbage collector is paused while they stamp
receipts (the instrument must not add pauses); the server's is not, so its
full collections, which take tens of milliseconds with 1000 connections
open, show in p99 and max. The file-descriptor limit is raised to the hard
limit here, before the server is started, so the server inherits it (the
server does not raise its own).

`--pin` (the headline figure, as a cell's controller has its own core): the server runs on one core
and this process (the clients and the driver) on another
(`os.sched_setaffinity`; the server's is set in its process before it starts,
so every thread it starts inherits it). Unpinned, the two share both cores
and a receipt waits whenever the crowd holds the core the server needs: the
figure measures the crowd as much as the server. Each result row says which.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import itertools
import json
import os
import resource
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import httpx
import psutil
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from bench.report import emit, percentiles_ms
from tests.processes import server_process
from tests.serving import admin_headers, free_port

CLOSE_SLOW = 4001
DELIVERY_TIMEOUT_S = 10.0
CONNECT_CONCURRENCY = 50
FDS_PER_CLIENT = 2  # the client's socket here and the server's socket in its process
SPARE_FDS = 200


class Receipt(NamedTuple):
    """What a client keeps of one message (a tuple of atoms: nothing for the collector)."""

    received_at: float
    sent_at: float
    type: str
    seq: int
    event_id: str


@dataclass
class Client:
    """One WebSocket client and everything it received after subscribing."""

    received: list[Receipt] = field(default_factory=list)
    close_code: int | None = None
    close_reason: str = ""
    closing: bool = False


@dataclass
class Tally:
    """How many clients have each transition, for pacing the driver."""

    counts: Counter[str] = field(default_factory=Counter)
    open_clients: int = 0


def pinning(pin: bool) -> tuple[set[int], set[int]] | None:
    """(server cores, client cores) when pinning and at least two cores are ours, else None."""
    if not pin:
        return None
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        raise SystemExit("--pin needs two cores: one for the server, one for the clients")
    return {cores[-1]}, set(cores[:-1])


def raise_fd_limit(needed: int) -> int:
    """Raise RLIMIT_NOFILE's soft limit to the hard limit; the limit in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, needed)
    if soft < target:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    if soft < needed:
        raise SystemExit(f"{needed} file descriptors needed, the hard limit allows {soft}")
    return soft


async def open_client(url: str, headers: dict[str, str], compression: bool) -> ClientConnection:
    """Connect, take the snapshot, subscribe to state_changed and wait for the ack."""
    ws = await connect(
        url,
        additional_headers=headers,
        compression="deflate" if compression else None,
        proxy=None,
        ping_interval=None,  # the server pings; the clients only answer
        open_timeout=30,
    )
    snapshot = json.loads(await ws.recv())
    assert snapshot["type"] == "snapshot", snapshot
    await ws.send(json.dumps({"type": "subscribe", "types": ["state_changed"]}))
    while json.loads(await ws.recv())["type"] != "subscribed":
        pass
    return ws


async def read(ws: ClientConnection, client: Client, tally: Tally) -> None:
    """Stamp and keep every message until the connection closes."""
    try:
        while True:
            raw = await ws.recv()
            received_at = time.time()
            message = json.loads(raw)
            event_id = message.get("event_id", "")
            client.received.append(
                Receipt(received_at, message["time"], message["type"], message["seq"], event_id)
            )
            tally.counts[event_id] += 1
    except ConnectionClosed as closed:
        if not client.closing and closed.rcvd is not None:
            client.close_code, client.close_reason = closed.rcvd.code, closed.rcvd.reason
    finally:
        tally.open_clients -= 1


async def drive(http: httpx.AsyncClient, transitions: int, tally: Tally) -> list[str]:
    """Alternate e-stop and reset, each once every open client has the previous; the event ids."""
    caused = []
    for index in range(transitions):
        response = await http.post("/estop" if index % 2 == 0 else "/reset")
        body = response.json()
        if response.status_code != 202:
            raise RuntimeError(f"command refused: {response.status_code} {body}")
        event_id = body["event_id"]
        started = time.monotonic()
        while tally.counts[event_id] < tally.open_clients:
            if time.monotonic() - started > DELIVERY_TIMEOUT_S:
                break
            await asyncio.sleep(0.001)
        caused.append(event_id)
    return caused


def delivered_all(client: Client, expected: list[str]) -> bool:
    """Exactly the transitions caused, in order, with strictly increasing seq."""
    messages = [r for r in client.received if r.type == "state_changed"]
    seqs = [r.seq for r in messages]
    in_order = all(a < b for a, b in itertools.pairwise(seqs))
    return in_order and [r.event_id for r in messages] == expected


def summarise(clients: list[Client], expected: list[str]) -> dict[str, Any]:
    samples: list[float] = []
    slowest: dict[str, float] = {}
    for client in clients:
        for receipt in client.received:
            if receipt.type != "state_changed":
                continue
            latency = receipt.received_at - receipt.sent_at
            samples.append(latency)
            slowest[receipt.event_id] = max(slowest.get(receipt.event_id, 0.0), latency)
    complete = sum(delivered_all(c, expected) for c in clients)
    dropped = sum(c.close_code == CLOSE_SLOW for c in clients)
    return {
        **percentiles_ms(samples),
        "everyone_p99_ms": percentiles_ms(list(slowest.values()))["p99_ms"],
        "complete": complete,
        "dropped_told": dropped,
        "missing": len(clients) - complete - dropped,
    }


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """No garbage-collector pause in the clients while they stamp receipts.

    The instrument must not add pauses of its own: a full collection over the
    thousand connections' objects takes tens of milliseconds. The server's
    collector is left alone: its pauses are part of what is measured.
    """
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


async def wait_for_no_clients(http: httpx.AsyncClient) -> None:
    """The server has let go of every connection (the next round starts clean)."""
    deadline = time.monotonic() + 30
    while (await http.get("/health")).json()["websocket_clients"] != 0:
        if time.monotonic() > deadline:
            raise RuntimeError("the server still counts WebSocket clients 30 s after closing")
        await asyncio.sleep(0.05)


async def one_round(
    base: str, headers: dict[str, str], count: int, transitions: int, compression: bool, pid: int
) -> dict[str, Any]:
    url = base.replace("http://", "ws://") + "/ws"
    gate = asyncio.Semaphore(CONNECT_CONCURRENCY)

    async def opened() -> ClientConnection:
        async with gate:
            return await open_client(url, headers, compression)

    sockets = await asyncio.gather(*(opened() for _ in range(count)))
    clients = [Client() for _ in sockets]
    tally = Tally(open_clients=count)
    pairs = zip(sockets, clients, strict=True)
    readers = [asyncio.create_task(read(ws, client, tally)) for ws, client in pairs]
    server = psutil.Process(pid)
    server_rss_mb = server.memory_info().rss / 2**20  # with every client connected
    server_cpu, client_cpu = sum(server.cpu_times()[:2]), time.process_time()
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=30) as http:
        with collector_paused():
            caused = await drive(http, transitions, tally)
        server_cpu = sum(server.cpu_times()[:2]) - server_cpu
        client_cpu = time.process_time() - client_cpu
        for client in clients:
            client.closing = client.close_code is None
        await asyncio.gather(*(ws.close() for ws in sockets), return_exceptions=True)
        await asyncio.gather(*readers)
        await wait_for_no_clients(http)
    return {
        "clients": count,
        "transitions": len(caused),
        **summarise(clients, caused),
        "server_rss_mb": round(server_rss_mb, 1),
        "server_cpu_s": round(server_cpu, 2),
        "client_cpu_s": round(client_cpu, 2),
    }


async def wait_until_idle(base: str, headers: dict[str, str]) -> None:
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=10) as http:
        deadline = time.monotonic() + 60
        while (await http.get("/state")).json()["state"] != "IDLE":
            if time.monotonic() > deadline:
                raise RuntimeError("the cell did not reach IDLE within 60 s")
            await asyncio.sleep(0.05)


async def run(
    base: str, data_dir: Path, counts: list[int], transitions: int, compression: bool, pid: int
) -> list[dict[str, Any]]:
    headers = admin_headers(data_dir)
    await wait_until_idle(base, headers)
    return [
        await one_round(base, headers, count, transitions, compression, pid) for count in counts
    ]


def run_loop(coroutine: Coroutine[Any, Any, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Run in uvloop when it is installed (as uvicorn[standard] installs it): cheaper clients."""
    factory: Callable[[], asyncio.AbstractEventLoop] | None = None
    with contextlib.suppress(ImportError):
        import uvloop

        factory = uvloop.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(coroutine)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--clients", default="10,100,1000", help="client counts, comma-separated")
    parser.add_argument("--transitions", type=int, default=200, help="transitions per count")
    parser.add_argument("--no-compression", action="store_true", help="do not offer deflate")
    parser.add_argument("--name", default="ws_fanout", help="results file name (without .json)")
    parser.add_argument(
        "--pin",
        action="store_true",
        help="the server on the last core, the clients on the others (the headline figure)",
    )
    args = parser.parse_args(argv)
    cores = pinning(args.pin)
    counts = [int(c) for c in args.clients.split(",")]
    fd_limit = raise_fd_limit(FDS_PER_CLIENT * max(counts) + SPARE_FDS)
    port = free_port()
    allowed = str(max(counts) + 10)  # every client uses the admin token: raise its limit too
    env = {
        "GLUE_APP_MAX_BROADCAST_CLIENTS": allowed,
        "GLUE_APP_MAX_BROADCAST_CLIENTS_PER_TOKEN": allowed,
        # every client connects from 127.0.0.1: the per-address bound would refuse most
        "GLUE_APP_HTTP_MAX_CONNECTIONS": str(max(counts) + 100),
        "GLUE_APP_HTTP_MAX_CONNECTIONS_PER_ADDRESS": str(max(counts) + 100),
    }
    with (
        tempfile.TemporaryDirectory(prefix="bench-ws-") as tmp,
        server_process(
            port,
            Path(tmp),
            env=env,
            preexec_fn=(lambda: os.sched_setaffinity(0, cores[0])) if cores else None,
        ) as process,
    ):
        if cores:
            os.sched_setaffinity(0, cores[1])
        rows = run_loop(
            run(
                f"http://127.0.0.1:{port}",
                Path(tmp),
                counts,
                args.transitions,
                not args.no_compression,
                process.pid,
            )
        )
    extra = {
        "transitions_per_count": args.transitions,
        "compression": "none" if args.no_compression else "permessage-deflate offered",
        "fd_limit": fd_limit,
        "target": "1000 clients: p99 < 50 ms, missing = 0",
        "pinned": (
            {"server_cores": sorted(cores[0]), "client_cores": sorted(cores[1])}
            if cores
            else "no: server and clients share every core"
        ),
    }
    emit(args.name, rows, extra)
    return rows


if __name__ == "__main__":
    main()
